//! What travels in the latency benchmark, for every transport.
//!
//! Every message carries its index `k` (0, 1, ...; [`END`] ends a case): in the payload's first
//! 8 bytes as `k` and in its last 8 bytes as `!k` (little-endian), so each receiver checks the
//! size and that both ends of the payload arrived. Times are CLOCK_MONOTONIC ns, shared by all
//! processes of the machine: `origin_ns` = when the producer sent the message (first hop),
//! `publish_ns` = when the sender of this hop sent it.
//!
//! Socket framing (integers little-endian `u64`):
//! - `socket-raw`: a [`RawHeader`] (`index`, `origin_ns`, `publish_ns`, `len`), then `len` payload bytes.
//! - `socket-bincode`: `len`, then `len` bytes of bincode (serde, standard config) of a [`BincodeMsg`]
//!   whose payload is `size / 4` `f32` values (a point cloud or depth image as a copy-based
//!   pipeline would serialise it); the index is in the bit patterns of its first and last value.

use std::io::{Read, Write};
use std::mem::MaybeUninit;

use anyhow::{Context as _, ensure};
use serde::{Deserialize, Serialize};

/// Index of the message that ends a case (relays forward it, then report and exit).
pub const END: u64 = u64::MAX;

/// Writes the index into the first and last 8 bytes of an iceoryx2 payload (at least 16 bytes).
pub fn put_index(payload: &mut [MaybeUninit<u8>], index: u64) {
    let n = payload.len();
    for (dst, b) in payload[..8].iter_mut().zip(index.to_le_bytes()) {
        dst.write(b);
    }
    for (dst, b) in payload[n - 8..].iter_mut().zip((!index).to_le_bytes()) {
        dst.write(b);
    }
}

/// Reads the index of an iceoryx2 payload written by [`put_index`]; `None` if it is shorter than
/// 16 bytes or the two ends disagree.
pub fn get_index(payload: &[MaybeUninit<u8>]) -> Option<u64> {
    let n = payload.len();
    if n < 16 {
        return None;
    }
    let read = |s: &[MaybeUninit<u8>]| {
        let mut b = [0u8; 8];
        for (d, v) in b.iter_mut().zip(s) {
            // SAFETY: the sender wrote these 16 bytes with `put_index` before sending (the
            // protocol of this benchmark; every sender in it does).
            *d = unsafe { v.assume_init() };
        }
        u64::from_le_bytes(b)
    };
    let (head, tail) = (read(&payload[..8]), read(&payload[n - 8..]));
    (head == !tail).then_some(head)
}

/// The same for a byte buffer (socket-raw).
pub fn put_index_bytes(payload: &mut [u8], index: u64) {
    let n = payload.len();
    payload[..8].copy_from_slice(&index.to_le_bytes());
    payload[n - 8..].copy_from_slice(&(!index).to_le_bytes());
}

/// The same for a byte buffer (socket-raw).
pub fn get_index_bytes(payload: &[u8]) -> Option<u64> {
    let n = payload.len();
    if n < 16 {
        return None;
    }
    let head = u64::from_le_bytes(payload[..8].try_into().ok()?);
    let tail = u64::from_le_bytes(payload[n - 8..].try_into().ok()?);
    (head == !tail).then_some(head)
}

/// The same for an `f32` payload (socket-bincode): the low 32 bits of the index in the bit pattern
/// of the first value, their complement in the last (at least 2 values).
pub fn put_index_f32(payload: &mut [f32], index: u64) {
    let n = payload.len();
    payload[0] = f32::from_bits(index as u32);
    payload[n - 1] = f32::from_bits(!(index as u32));
}

/// Reads [`put_index_f32`]'s index (its low 32 bits; [`END`] reads back as `u32::MAX`).
pub fn get_index_f32(payload: &[f32]) -> Option<u64> {
    let n = payload.len();
    if n < 2 {
        return None;
    }
    let (head, tail) = (payload[0].to_bits(), payload[n - 1].to_bits());
    (head == !tail).then_some(if head == u32::MAX { END } else { u64::from(head) })
}

/// Reads every byte of a payload (a wrapping sum of its 8-byte words): what `--touch` makes each
/// receiver do before it takes its receive time.
pub fn touch_bytes(payload: &[u8]) -> u64 {
    let mut words = payload.chunks_exact(8);
    let sum =
        words.by_ref().fold(0u64, |acc, w| acc.wrapping_add(u64::from_le_bytes(w.try_into().unwrap_or_default())));
    words.remainder().iter().fold(sum, |acc, &b| acc.wrapping_add(u64::from(b)))
}

/// An iceoryx2 payload whose every byte was written by its sender, as bytes.
///
/// # Safety
/// Every byte of `payload` must have been initialised (in this benchmark: the producer always
/// writes the whole payload, and relays do under `--touch`).
pub unsafe fn assume_init_bytes(payload: &[MaybeUninit<u8>]) -> &[u8] {
    // SAFETY: `MaybeUninit<u8>` has the layout of `u8`; the caller guarantees initialisation.
    unsafe { std::slice::from_raw_parts(payload.as_ptr().cast::<u8>(), payload.len()) }
}

/// Fills a payload with a cheap pattern (the producer's "sensor data"; not timed).
pub fn fill_pattern(payload: &mut [u8], index: u64) {
    let mut x = index.wrapping_mul(0x9E37_79B9_7F4A_7C15) | 1;
    for chunk in payload.chunks_mut(8) {
        x ^= x << 13;
        x ^= x >> 7;
        x ^= x << 17;
        let bytes = x.to_le_bytes();
        chunk.copy_from_slice(&bytes[..chunk.len()]);
    }
}

/// Header of a socket-raw message.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct RawHeader {
    /// Message index ([`END`] ends the case).
    pub index: u64,
    /// When the producer sent the message, ns.
    pub origin_ns: u64,
    /// When this hop's sender started writing, ns.
    pub publish_ns: u64,
    /// Payload bytes that follow.
    pub len: u64,
}

impl RawHeader {
    /// Encoded size, bytes.
    pub const SIZE: usize = 32;

    /// Little-endian encoding.
    pub fn to_bytes(self) -> [u8; Self::SIZE] {
        let mut b = [0u8; Self::SIZE];
        for (i, v) in [self.index, self.origin_ns, self.publish_ns, self.len].into_iter().enumerate() {
            b[i * 8..i * 8 + 8].copy_from_slice(&v.to_le_bytes());
        }
        b
    }

    /// Decodes [`RawHeader::to_bytes`].
    pub fn from_bytes(b: &[u8; Self::SIZE]) -> Self {
        let w = |i: usize| u64::from_le_bytes(b[i * 8..i * 8 + 8].try_into().unwrap_or_default());
        Self { index: w(0), origin_ns: w(1), publish_ns: w(2), len: w(3) }
    }
}

/// Reads one socket-raw message into `buf` (resized to the payload); returns its header.
pub fn read_raw(stream: &mut impl Read, buf: &mut Vec<u8>, max_len: usize) -> anyhow::Result<RawHeader> {
    let mut hb = [0u8; RawHeader::SIZE];
    stream.read_exact(&mut hb).context("reading a socket-raw header")?;
    let h = RawHeader::from_bytes(&hb);
    let len = usize::try_from(h.len).ok().filter(|&l| l <= max_len);
    let len = len.with_context(|| format!("socket-raw message of {} bytes, at most {max_len} expected", h.len))?;
    buf.resize(len, 0);
    stream.read_exact(buf).context("reading a socket-raw payload")?;
    Ok(h)
}

/// Writes one socket-raw message (header stamped by the caller, then the payload).
pub fn write_raw(stream: &mut impl Write, header: RawHeader, payload: &[u8]) -> anyhow::Result<()> {
    stream.write_all(&header.to_bytes()).context("writing a socket-raw header")?;
    stream.write_all(payload).context("writing a socket-raw payload")
}

/// A socket-bincode message.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct BincodeMsg {
    /// Message index ([`END`] ends the case).
    pub index: u64,
    /// When the producer sent the message, ns.
    pub origin_ns: u64,
    /// When this hop's sender started encoding, ns.
    pub publish_ns: u64,
    /// The payload, `size / 4` values.
    pub payload: Vec<f32>,
}

fn bincode_config() -> bincode::config::Configuration {
    bincode::config::standard()
}

/// Encodes `msg` behind an 8-byte length into `buf` (reused) and writes it.
pub fn write_bincode(stream: &mut impl Write, msg: &BincodeMsg, buf: &mut Vec<u8>) -> anyhow::Result<()> {
    buf.clear();
    buf.extend_from_slice(&[0; 8]);
    bincode::serde::encode_into_std_write(msg, buf, bincode_config()).context("bincode encoding")?;
    let len = (buf.len() - 8) as u64;
    buf[..8].copy_from_slice(&len.to_le_bytes());
    stream.write_all(buf).context("writing a socket-bincode message")
}

/// Reads and decodes one socket-bincode message (`buf` is reused for the encoded bytes).
pub fn read_bincode(stream: &mut impl Read, buf: &mut Vec<u8>, max_len: usize) -> anyhow::Result<BincodeMsg> {
    let mut lb = [0u8; 8];
    stream.read_exact(&mut lb).context("reading a socket-bincode length")?;
    let raw = u64::from_le_bytes(lb);
    // An f32 takes 4 bytes in bincode; allow for the header and the vector's length prefix.
    let len = usize::try_from(raw).ok().filter(|&l| l <= max_len + 64);
    let len = len.with_context(|| format!("socket-bincode message of {raw} bytes, at most {max_len} expected"))?;
    buf.resize(len, 0);
    stream.read_exact(buf).context("reading a socket-bincode message")?;
    let (msg, used): (BincodeMsg, usize) =
        bincode::serde::decode_from_slice(buf, bincode_config()).context("decoding a socket-bincode message")?;
    ensure!(used == len, "socket-bincode message: {used} of {len} bytes decoded");
    Ok(msg)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_index_round_trips_in_every_payload_form_and_a_torn_payload_is_detected() {
        let mut p = vec![MaybeUninit::new(0u8); 64];
        put_index(&mut p, 12345);
        assert_eq!(get_index(&p), Some(12345));
        p[63] = MaybeUninit::new(1);
        assert_eq!(get_index(&p), None);
        put_index(&mut p, END);
        assert_eq!(get_index(&p), Some(END));

        let mut b = vec![0u8; 100];
        fill_pattern(&mut b, 7);
        put_index_bytes(&mut b, 99);
        assert_eq!(get_index_bytes(&b), Some(99));
        assert_eq!(get_index_bytes(&b[..50]), None);

        let mut f = vec![0f32; 16];
        put_index_f32(&mut f, 42);
        assert_eq!(get_index_f32(&f), Some(42));
        put_index_f32(&mut f, END);
        assert_eq!(get_index_f32(&f), Some(END));
    }

    #[test]
    fn socket_framings_round_trip() {
        let mut wire = Vec::new();
        let mut payload = vec![0u8; 48];
        put_index_bytes(&mut payload, 3);
        let h = RawHeader { index: 3, origin_ns: 10, publish_ns: 20, len: 48 };
        write_raw(&mut wire, h, &payload).unwrap();
        let mut buf = Vec::new();
        assert_eq!(read_raw(&mut wire.as_slice(), &mut buf, 1 << 20).unwrap(), h);
        assert_eq!(buf, payload);
        assert!(read_raw(&mut wire.as_slice(), &mut buf, 16).is_err(), "oversized message accepted");

        let msg = BincodeMsg { index: 5, origin_ns: 1, publish_ns: 2, payload: vec![1.5; 10] };
        let (mut wire, mut scratch) = (Vec::new(), Vec::new());
        write_bincode(&mut wire, &msg, &mut scratch).unwrap();
        assert_eq!(read_bincode(&mut wire.as_slice(), &mut buf, 40).unwrap(), msg);
    }
}
