//! A persistent (copy-on-write) map from landmark id to landmark, shared between particles.
//!
//! The scaling idea of Montemerlo et al. (FastSLAM, AAAI 2002): keep each particle's landmarks
//! in a balanced tree whose subtrees are shared between particles, so that resampling copies a
//! pointer instead of a whole map, and updating a landmark copies only the O(log M) nodes on its
//! path. Here the tree is an 8-ary trie over the 32-bit landmark id (depth ⌈log8(max id)⌉, so it
//! is balanced by construction): inner nodes hold 8 `Arc` children, leaves hold `Arc<V>`.
//! [`PersistentMap::get_mut`] uses `Arc::make_mut` along the path: a node shared with another
//! particle is copied once, a node this particle already owns is changed in place — so many
//! updates of one particle in one frame share the copies near the root.
//!
//! Why 8: copying a node costs one atomic reference-count increment per child (and a decrement
//! when the copy is freed), ~20 cycles each even uncontended, and an update copies one node per
//! level; width × depth is smallest near width 3-8. Measured with `fastslam_bench` (N = 1000,
//! M = 10k, process CPU per frame): 16-ary 33 ms, 8-ary 30 ms, 4-ary 34 ms. Values stored inline
//! in the leaf nodes (no `Arc` per landmark) were slower still (49 ms): every update then copies
//! 8 landmarks, and the memory traffic outweighs the saved reference counts.

use std::sync::Arc;

const BITS: u32 = 3;
const WIDTH: usize = 1 << BITS;
const MASK: u32 = (WIDTH as u32) - 1;

#[derive(Clone)]
enum Node<V> {
    Inner([Option<Arc<Node<V>>>; WIDTH]),
    Leaves([Option<Arc<V>>; WIDTH]),
}

impl<V> Node<V> {
    fn empty(level: u32) -> Self {
        if level == 0 { Node::Leaves(Default::default()) } else { Node::Inner(Default::default()) }
    }
}

/// A persistent map `u32 → V`; cloning it is O(1) and shares all structure.
#[derive(Clone)]
pub struct PersistentMap<V> {
    root: Option<Arc<Node<V>>>,
    /// Levels below the root's level (0: the root holds leaves).
    level: u32,
    len: usize,
}

impl<V> Default for PersistentMap<V> {
    fn default() -> Self {
        Self { root: None, level: 0, len: 0 }
    }
}

impl<V: std::fmt::Debug + Clone> std::fmt::Debug for PersistentMap<V> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_map().entries(self.iter()).finish()
    }
}

fn slot(id: u32, level: u32) -> usize {
    ((id >> (BITS * level)) & MASK) as usize
}

impl<V: Clone> PersistentMap<V> {
    /// An empty map.
    pub fn new() -> Self {
        Self::default()
    }

    /// Number of entries.
    pub fn len(&self) -> usize {
        self.len
    }

    /// True when empty.
    pub fn is_empty(&self) -> bool {
        self.len == 0
    }

    fn capacity_bits(&self) -> u32 {
        BITS * (self.level + 1)
    }

    fn fits(&self, id: u32) -> bool {
        self.capacity_bits() >= 32 || (id >> self.capacity_bits()) == 0
    }

    /// The entry of `id`.
    pub fn get(&self, id: u32) -> Option<&V> {
        if !self.fits(id) {
            return None;
        }
        let mut node = self.root.as_deref()?;
        let mut level = self.level;
        loop {
            match node {
                Node::Inner(children) => {
                    node = children[slot(id, level)].as_deref()?;
                    level -= 1;
                }
                Node::Leaves(leaves) => return leaves[slot(id, 0)].as_deref(),
            }
        }
    }

    /// The entry of `id`, mutable: copies the shared nodes on its path (and the entry itself if
    /// another map shares it), mutates owned ones in place.
    pub fn get_mut(&mut self, id: u32) -> Option<&mut V> {
        // (For an absent id this may copy shared nodes on the way down; harmless.)
        if !self.fits(id) {
            return None;
        }
        let mut node = Arc::make_mut(self.root.as_mut()?);
        let mut level = self.level;
        loop {
            match node {
                Node::Inner(children) => {
                    node = Arc::make_mut(children[slot(id, level)].as_mut()?);
                    level -= 1;
                }
                Node::Leaves(leaves) => return leaves[slot(id, 0)].as_mut().map(Arc::make_mut),
            }
        }
    }

    /// Inserts or replaces the entry of `id`; returns the old value.
    pub fn insert(&mut self, id: u32, value: V) -> Option<V> {
        while !self.fits(id) {
            // Grow: the old root becomes child 0 of a new root one level up.
            let old = self.root.take();
            self.level += 1;
            let mut children: [Option<Arc<Node<V>>>; WIDTH] = Default::default();
            children[0] = old;
            self.root = Some(Arc::new(Node::Inner(children)));
        }
        let level0 = self.level;
        let mut node = Arc::make_mut(self.root.get_or_insert_with(|| Arc::new(Node::empty(level0))));
        let mut level = self.level;
        let old = loop {
            match node {
                Node::Inner(children) => {
                    let child = children[slot(id, level)].get_or_insert_with(|| Arc::new(Node::empty(level - 1)));
                    node = Arc::make_mut(child);
                    level -= 1;
                }
                Node::Leaves(leaves) => break leaves[slot(id, 0)].replace(Arc::new(value)),
            }
        };
        if old.is_none() {
            self.len += 1;
        }
        old.map(|a| Arc::try_unwrap(a).unwrap_or_else(|a| (*a).clone()))
    }

    /// Removes the entry of `id`; returns it.
    pub fn remove(&mut self, id: u32) -> Option<V> {
        self.get(id)?;
        let mut node = Arc::make_mut(self.root.as_mut()?);
        let mut level = self.level;
        let old = loop {
            match node {
                Node::Inner(children) => {
                    node = Arc::make_mut(children[slot(id, level)].as_mut()?);
                    level -= 1;
                }
                Node::Leaves(leaves) => break leaves[slot(id, 0)].take(),
            }
        };
        self.len -= 1;
        old.map(|a| Arc::try_unwrap(a).unwrap_or_else(|a| (*a).clone()))
    }

    /// Entries in ascending id order.
    pub fn iter(&self) -> impl Iterator<Item = (u32, &V)> {
        let mut out = Vec::with_capacity(self.len);
        if let Some(root) = self.root.as_deref() {
            collect(root, self.level, 0, &mut out);
        }
        out.into_iter()
    }

    /// True when both maps share the same root (nothing was copied since one was cloned from
    /// the other).
    pub fn shares_root_with(&self, other: &Self) -> bool {
        match (&self.root, &other.root) {
            (Some(a), Some(b)) => Arc::ptr_eq(a, b),
            (None, None) => true,
            _ => false,
        }
    }
}

fn collect<'a, V>(node: &'a Node<V>, level: u32, prefix: u32, out: &mut Vec<(u32, &'a V)>) {
    match node {
        Node::Inner(children) => {
            for (i, c) in children.iter().enumerate() {
                if let Some(c) = c.as_deref() {
                    collect(c, level - 1, prefix | ((i as u32) << (BITS * level)), out);
                }
            }
        }
        Node::Leaves(leaves) => {
            for (i, l) in leaves.iter().enumerate() {
                if let Some(v) = l.as_deref() {
                    out.push((prefix | i as u32, v));
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;
    use std::collections::BTreeMap;

    proptest! {
        #[test]
        fn behaves_like_a_btreemap(ops in proptest::collection::vec((0u8..3, 0u32..5000, any::<i32>()), 0..400)) {
            let mut a = PersistentMap::new();
            let mut b = BTreeMap::new();
            let mut snapshots = vec![];
            for (op, id, v) in ops {
                match op {
                    0 => prop_assert_eq!(a.insert(id, v), b.insert(id, v)),
                    1 => prop_assert_eq!(a.remove(id), b.remove(&id)),
                    _ => {
                        if let Some(x) = a.get_mut(id) { *x = v; }
                        if let Some(x) = b.get_mut(&id) { *x = v; }
                    }
                }
                prop_assert_eq!(a.len(), b.len());
                snapshots.push((a.clone(), b.clone()));
            }
            // Every snapshot is unchanged by later edits: persistence.
            for (a, b) in snapshots {
                let av: Vec<_> = a.iter().map(|(k, v)| (k, *v)).collect();
                let bv: Vec<_> = b.iter().map(|(k, v)| (*k, *v)).collect();
                prop_assert_eq!(av, bv);
            }
        }
    }

    #[test]
    fn clones_share_structure_until_written_and_writes_copy_only_the_path() {
        let mut a = PersistentMap::new();
        for id in 0..10_000u32 {
            a.insert(id, [id as f64; 12]);
        }
        let b = a.clone();
        assert!(a.shares_root_with(&b));
        a.get_mut(1234).unwrap()[0] = -1.0;
        assert!(!a.shares_root_with(&b));
        assert_eq!(b.get(1234).unwrap()[0], 1234.0, "the clone is untouched");
        assert_eq!(a.get(1234).unwrap()[0], -1.0);
        // Every landmark but the written one is still shared between the two maps.
        let shared = a.iter().zip(b.iter()).filter(|((_, x), (_, y))| std::ptr::eq(*x, *y)).count();
        assert_eq!(shared, 9_999);
    }

    #[test]
    fn ids_beyond_the_current_depth_grow_the_tree() {
        let mut m = PersistentMap::new();
        m.insert(3, 'a');
        m.insert(u32::MAX, 'z');
        m.insert(70_000, 'm');
        assert_eq!(m.get(3), Some(&'a'));
        assert_eq!(m.get(u32::MAX), Some(&'z'));
        assert_eq!(m.get(70_000), Some(&'m'));
        assert_eq!(m.get(4), None);
        assert_eq!(m.iter().map(|(k, _)| k).collect::<Vec<_>>(), vec![3, 70_000, u32::MAX]);
    }
}
