//! The pool of send buffers messages are copied into for Zenoh (returned when Zenoh drops them).

use crate::lock;
use std::sync::{Arc, Mutex};

/// Buffers that messages are copied into for Zenoh, returned when Zenoh drops them.
#[derive(Clone, Default)]
pub(crate) struct SendBuffers(pub(crate) Arc<Mutex<Vec<Vec<u8>>>>);

/// A send buffer on loan to Zenoh: returns itself to its pool when dropped.
pub(crate) struct SendBuffer {
    pub(crate) data: Vec<u8>,
    pub(crate) pool: SendBuffers,
}

impl AsRef<[u8]> for SendBuffer {
    fn as_ref(&self) -> &[u8] {
        &self.data
    }
}

impl Drop for SendBuffer {
    fn drop(&mut self) {
        let mut pool = lock(&self.pool.0);
        // Zenoh drops a put's payload once it is serialized, so one or two are in use at a time.
        if pool.len() < 4 {
            pool.push(std::mem::take(&mut self.data));
        }
    }
}

impl SendBuffers {
    /// `parts` copied, one after the other, into a reused buffer.
    pub(crate) fn payload(&self, parts: &[&[u8]]) -> zenoh::bytes::ZBytes {
        let len = parts.iter().map(|p| p.len()).sum();
        let mut data = lock(&self.0).pop().unwrap_or_default();
        data.clear();
        data.reserve(len);
        for p in parts {
            data.extend_from_slice(p);
        }
        bytes::Bytes::from_owner(SendBuffer { data, pool: self.clone() }).into()
    }
}
