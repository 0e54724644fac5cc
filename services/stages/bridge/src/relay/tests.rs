//! Unit tests of the parent module.

use super::*;

#[test]
fn a_zid_is_32_lowercase_hex_digits_without_a_leading_zero_and_differs_per_name() {
    for n in ["auv1", "auv2", "base", ""] {
        let h = zid_hex(n);
        assert_eq!(h.len(), 32, "{n}: {h}");
        assert!(!h.starts_with('0'));
        assert!(h.chars().all(|c| c.is_ascii_digit() || ('a'..='f').contains(&c)));
    }
    assert_ne!(zid_of("auv1"), zid_of("auv2"));
    // Pinned: peers of users' own compute it (docs/security.md's recipe gives this too).
    assert_eq!(zid_hex("auv2"), "e7dcc051d576d4055cbf2766dd8d3631");
    assert_eq!(zid_of("auv1"), zid_of("auv1"));
}

#[test]
fn counts_keep_at_most_max_pairs_apart_then_count_the_rest_together() {
    let mut c = BTreeMap::new();
    for i in 0..MAX_PAIRS + 10 {
        count(&mut c, &format!("10.0.{}.{}", i / 256, i % 256), "TLS handshake failed");
    }
    assert_eq!(count(&mut c, "10.0.0.1", "TLS handshake failed"), 2, "a pair kept apart goes on counting");
    assert_eq!(c.len(), MAX_PAIRS + 1);
    assert_eq!(c[&(OTHER_PEERS.to_string(), "TLS handshake failed".to_string())], 10);
    assert_eq!(c.values().sum::<u64>(), (MAX_PAIRS + 11) as u64, "every link counted");
}

#[test]
fn the_first_zid_is_read_from_an_init_message_and_anything_else_is_refused() {
    let zid: u128 = 0x8123_4567_89ab_cdef_0011_2233_4455_6677;
    let mut m = vec![0, 0, 0x01 | 0x20, 0x09, (15 << 4) | 0x01];
    m.extend_from_slice(&zid.to_le_bytes());
    m.extend_from_slice(&[1, 2, 3]);
    let len = (m.len() - 2) as u16;
    m[..2].copy_from_slice(&len.to_le_bytes());
    assert_eq!(first_zid(&m), Ok(Some(zid)));
    for k in 0..m.len().min(20) {
        assert_eq!(first_zid(&m[..k]), Ok(None), "{k} bytes");
    }
    // A short id (Zenoh drops the most significant zero bytes).
    let short = [3u8, 0, 0x01, 0x09, 0x01 << 4, 0x34, 0x12];
    assert_eq!(first_zid(&short), Ok(Some(0x1234)));
    // Not an InitSyn/InitAck (a frame: id 0x05).
    assert!(first_zid(&[3, 0, 0x05, 0x09, 0x10, 1, 2]).is_err());
}
