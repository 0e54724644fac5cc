//! Open-addressing hash set of packed 48-bit keys (linear probing, Fibonacci hashing).

const EMPTY: u64 = u64::MAX;

/// A set of `u64` values (never `u64::MAX`); keeps its allocation across [`KeySet::clear`].
#[derive(Debug, Clone)]
pub(crate) struct KeySet {
    slots: Vec<u64>,
    len: usize,
    shift: u32,
}

impl Default for KeySet {
    fn default() -> Self {
        Self::with_capacity_pow2(10)
    }
}

impl KeySet {
    fn with_capacity_pow2(bits: u32) -> Self {
        KeySet { slots: vec![EMPTY; 1 << bits], len: 0, shift: 64 - bits }
    }

    #[inline]
    fn slot(&self, k: u64) -> usize {
        (k.wrapping_mul(0x9E37_79B9_7F4A_7C15) >> self.shift) as usize
    }

    /// Inserts `k`; returns true when it was not present.
    #[inline]
    pub(crate) fn insert(&mut self, k: u64) -> bool {
        if (self.len + 1) * 2 > self.slots.len() {
            self.grow();
        }
        let mask = self.slots.len() - 1;
        let mut i = self.slot(k);
        loop {
            // `i` is always masked into range.
            let e = self.slots[i];
            if e == k {
                return false;
            }
            if e == EMPTY {
                self.slots[i] = k;
                self.len += 1;
                return true;
            }
            i = (i + 1) & mask;
        }
    }

    fn grow(&mut self) {
        let bits = 64 - self.shift + 1;
        let old = std::mem::replace(self, Self::with_capacity_pow2(bits));
        for k in old.slots.into_iter().filter(|&k| k != EMPTY) {
            self.insert(k);
        }
    }

    /// Number of elements.
    pub(crate) fn len(&self) -> usize {
        self.len
    }

    /// Removes all elements, keeping the allocation.
    pub(crate) fn clear(&mut self) {
        if self.len > 0 {
            self.slots.fill(EMPTY);
            self.len = 0;
        }
    }

    /// Iterates over the elements (in table order).
    pub(crate) fn iter(&self) -> impl Iterator<Item = u64> + '_ {
        self.slots.iter().copied().filter(|&k| k != EMPTY)
    }

    /// Heap bytes held.
    pub(crate) fn heap_bytes(&self) -> usize {
        self.slots.capacity() * 8
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::collections::HashSet;

    #[test]
    fn behaves_like_a_set() {
        let mut s = KeySet::default();
        let mut h = HashSet::new();
        let mut x = 12345u64;
        for _ in 0..20000 {
            x = x.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
            let k = (x >> 20) & 0x3FFF;
            assert_eq!(s.insert(k), h.insert(k));
        }
        assert_eq!(s.len(), h.len());
        let got: HashSet<u64> = s.iter().collect();
        assert_eq!(got, h);
        s.clear();
        assert_eq!(s.len(), 0);
        assert_eq!(s.iter().count(), 0);
    }
}
