//! CDR with its 4-byte encapsulation header, as every ROS 2 message travels (DDS payloads and
//! rosbag2's `cdr` message encoding): 2 bytes representation id (`00 00` big-endian CDR, `00 01`
//! little-endian CDR), 2 bytes options, then the message aligned from the byte after the header.
//! ROS 2 peers send XCDR1 ("plain" CDR); XCDR2 and parameter-list encodings are refused with an
//! error that names them.

use serde::{Deserialize, Serialize};

/// Why bytes are not a message of the expected type.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum CdrError {
    /// Shorter than the encapsulation header.
    #[error("{len} bytes: shorter than the 4-byte CDR encapsulation header")]
    TooShort {
        /// Bytes given.
        len: usize,
    },
    /// An encapsulation other than plain CDR.
    #[error("encapsulation {id:#06x} ({what}) is not supported: ROS 2 messages are plain CDR (0x0000 / 0x0001)")]
    Encapsulation {
        /// The representation id.
        id: u16,
        /// Its name.
        what: &'static str,
    },
    /// The body does not decode as the type (cut short, a bad length, a string that is not UTF-8).
    #[error("not a {type_name}: {reason}")]
    Body {
        /// The expected ROS 2 type.
        type_name: &'static str,
        /// What the decoder said.
        reason: String,
    },
    /// Encoding failed (never for the types of this crate).
    #[error("encoding failed: {0}")]
    Encode(String),
}

/// Representation id of little-endian plain CDR.
pub const CDR_LE: [u8; 4] = [0, 1, 0, 0];

/// The encapsulation of `bytes`: true for little-endian CDR, false for big-endian.
pub fn representation(bytes: &[u8]) -> Result<bool, CdrError> {
    if bytes.len() < 4 {
        return Err(CdrError::TooShort { len: bytes.len() });
    }
    let id = u16::from_be_bytes([bytes[0], bytes[1]]);
    match id {
        0x0000 => Ok(false),
        0x0001 => Ok(true),
        other => Err(CdrError::Encapsulation {
            id: other,
            what: match other {
                0x0002 | 0x0003 => "PL_CDR",
                0x0006 | 0x0007 => "XCDR2",
                0x0008 | 0x0009 => "D_CDR2",
                0x000a | 0x000b => "PL_CDR2",
                0x0004 | 0x0005 => "XML",
                _ => "unknown",
            },
        }),
    }
}

/// Decodes a message of type `T` (named `type_name` in errors) from encapsulated CDR. Byte
/// sequences in `T` ([`crate::msgs::Bytes`]) borrow from `bytes`.
pub fn decode<'a, T: Deserialize<'a>>(bytes: &'a [u8], type_name: &'static str) -> Result<T, CdrError> {
    let little = representation(bytes)?;
    let body = &bytes[4..];
    let r = if little {
        cdr_encoding::from_bytes::<T, byteorder::LittleEndian>(body)
    } else {
        cdr_encoding::from_bytes::<T, byteorder::BigEndian>(body)
    };
    r.map(|(t, _)| t).map_err(|e| CdrError::Body { type_name, reason: e.to_string() })
}

/// Encodes `msg` as little-endian CDR with its encapsulation header, appending to `out`.
pub fn encode_into<T: Serialize>(msg: &T, out: &mut Vec<u8>) -> Result<(), CdrError> {
    out.extend_from_slice(&CDR_LE);
    // Alignment counts from the byte after the header: serialize into a buffer of its own.
    let body = cdr_encoding::to_vec::<T, byteorder::LittleEndian>(msg).map_err(|e| CdrError::Encode(e.to_string()))?;
    out.extend_from_slice(&body);
    Ok(())
}

/// Encodes `msg` as little-endian CDR with its encapsulation header.
pub fn encode<T: Serialize>(msg: &T) -> Result<Vec<u8>, CdrError> {
    let mut out = Vec::new();
    encode_into(msg, &mut out)?;
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::Message;
    use crate::msgs::*;

    #[test]
    fn a_humble_range_without_variance_decodes_with_variance_unknown() {
        let h = RangeHumble {
            header: crate::convert::header(5, "buoy_1"),
            range: 12.5,
            max_range: 100.0,
            ..Default::default()
        };
        let r: Range = decode(&encode(&h).unwrap(), Range::TYPE_NAME).unwrap();
        assert_eq!((r.range, r.max_range, r.variance, r.header.frame_id.as_str()), (12.5, 100.0, 0.0, "buoy_1"));
        let j = Range { variance: 0.25, ..r.clone() };
        assert_eq!(decode::<Range>(&encode(&j).unwrap(), Range::TYPE_NAME).unwrap(), j);
    }

    #[test]
    fn big_endian_cdr_decodes_and_other_encapsulations_are_named() {
        let scan = LaserScan { ranges: vec![1.0, 2.5], angle_increment: 0.25, ..Default::default() };
        let mut be = vec![0, 0, 0, 0];
        be.extend(cdr_encoding::to_vec::<_, byteorder::BigEndian>(&scan).unwrap());
        assert_eq!(decode::<LaserScan>(&be, LaserScan::TYPE_NAME).unwrap(), scan);
        let mut x2 = encode(&scan).unwrap();
        x2[1] = 7;
        let e = decode::<LaserScan>(&x2, LaserScan::TYPE_NAME).unwrap_err().to_string();
        assert!(e.contains("XCDR2"), "{e}");
        assert!(matches!(decode::<LaserScan>(&[0, 1], "x"), Err(CdrError::TooShort { len: 2 })));
        let full = encode(&scan).unwrap();
        let e = decode::<LaserScan>(&full[..full.len() - 3], LaserScan::TYPE_NAME).unwrap_err();
        assert!(matches!(e, CdrError::Body { .. }), "{e}");
    }
}
