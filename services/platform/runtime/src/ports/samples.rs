//! What a port hands out: a received sample ([`Received`]) and a loaned one ([`Loaned`],
//! [`Loan`]), in shared memory or in process (the test harness's queues), read and written in place.

use super::*;

/// A received sample: in shared memory (read in place), or an in-process message.
pub enum Received<P: Payload + ?Sized, H: Header> {
    /// A sample in shared memory.
    Shm(Sample<ipc::Service, P, H>),
    /// An in-process message (see [`crate::testing`]).
    Local(H, Box<P>),
}

impl<P: Payload + ?Sized, H: Header> Received<P, H> {
    /// The user header.
    pub fn user_header(&self) -> &H {
        match self {
            Received::Shm(s) => s.user_header(),
            Received::Local(h, _) => h,
        }
    }

    /// The payload.
    pub fn payload(&self) -> &P {
        match self {
            Received::Shm(s) => P::sample_payload(s),
            Received::Local(_, p) => p,
        }
    }

    /// The id of the publisher that sent it (0 for an in-process message).
    pub fn publisher_id(&self) -> u128 {
        match self {
            Received::Shm(s) => s.origin().value(),
            Received::Local(..) => 0,
        }
    }
}

impl<P: Payload + ?Sized, H: Header> Deref for Received<P, H> {
    type Target = P;
    fn deref(&self) -> &P {
        self.payload()
    }
}

/// A written sample ready for [`Output::send`].
pub enum Loaned<P: Payload + ?Sized, H: Header> {
    /// Loaned in shared memory.
    Shm(SampleMut<ipc::Service, P, H>),
    /// An in-process message.
    Local(H, Box<P>),
}

impl<P: Payload + ?Sized, H: Header> Loaned<P, H> {
    /// The user header.
    pub fn user_header(&self) -> &H {
        match self {
            Loaned::Shm(s) => s.user_header(),
            Loaned::Local(h, _) => h,
        }
    }

    /// The user header, to write.
    pub fn user_header_mut(&mut self) -> &mut H {
        match self {
            Loaned::Shm(s) => s.user_header_mut(),
            Loaned::Local(h, _) => h,
        }
    }

    /// The payload.
    pub fn payload(&self) -> &P {
        match self {
            Loaned::Shm(s) => P::loaned_payload(s),
            Loaned::Local(_, p) => p,
        }
    }

    /// The payload, to write in place.
    pub fn payload_mut(&mut self) -> &mut P {
        match self {
            Loaned::Shm(s) => P::loaned_payload_mut(s),
            Loaned::Local(_, p) => p,
        }
    }
}

/// An uninitialised fixed-size sample ([`Output::loan_uninit`]).
pub enum Loan<T: Debug + ZeroCopySend + 'static, H: Header> {
    /// Loaned in shared memory.
    Shm(SampleMutUninit<ipc::Service, MaybeUninit<T>, H>),
    /// An in-process message.
    Local(H),
}

impl<T: Debug + ZeroCopySend + 'static, H: Header> Loan<T, H> {
    /// The user header, to write.
    pub fn user_header_mut(&mut self) -> &mut H {
        match self {
            Loan::Shm(s) => s.user_header_mut(),
            Loan::Local(h) => h,
        }
    }

    /// Writes the payload in place.
    pub fn write_payload(self, value: T) -> Loaned<T, H> {
        match self {
            Loan::Shm(s) => Loaned::Shm(s.write_payload(value)),
            Loan::Local(h) => Loaned::Local(h, Box::new(value)),
        }
    }
}

/// An uninitialised slice sample ([`Output::loan_slice_uninit`]).
pub enum SliceLoan<T: Debug + ZeroCopySend + 'static, H: Header> {
    /// Loaned in shared memory.
    Shm(SampleMutUninit<ipc::Service, [MaybeUninit<T>], H>),
    /// An in-process message.
    Local(H, Box<[MaybeUninit<T>]>),
}

impl<T: Debug + ZeroCopySend + 'static, H: Header> SliceLoan<T, H> {
    /// The user header, to write.
    pub fn user_header_mut(&mut self) -> &mut H {
        match self {
            SliceLoan::Shm(s) => s.user_header_mut(),
            SliceLoan::Local(h, _) => h,
        }
    }

    /// The uninitialised elements, to write in place before [`SliceLoan::assume_init`].
    pub fn payload_mut(&mut self) -> &mut [MaybeUninit<T>] {
        match self {
            SliceLoan::Shm(s) => s.payload_mut(),
            SliceLoan::Local(_, p) => p,
        }
    }

    /// Writes element `i` as `f(i)`, in place.
    pub fn write_from_fn(self, mut f: impl FnMut(usize) -> T) -> Loaned<[T], H> {
        match self {
            SliceLoan::Shm(s) => Loaned::Shm(s.write_from_fn(f)),
            SliceLoan::Local(h, p) => Loaned::Local(h, (0..p.len()).map(&mut f).collect()),
        }
    }

    /// Copies `values` (of the loaned length) in place.
    pub fn write_from_slice(self, values: &[T]) -> Loaned<[T], H>
    where
        T: Copy,
    {
        match self {
            SliceLoan::Shm(s) => Loaned::Shm(s.write_from_slice(values)),
            SliceLoan::Local(h, p) => {
                debug_assert_eq!(p.len(), values.len(), "write_from_slice: length of the loan");
                Loaned::Local(h, values.into())
            }
        }
    }

    /// Takes the elements as written.
    ///
    /// # Safety
    /// Every element must have been written (through [`SliceLoan::payload_mut`]), or `T` must
    /// be valid for any bytes (e.g. `MaybeUninit<u8>`).
    pub unsafe fn assume_init(self) -> Loaned<[T], H> {
        match self {
            // SAFETY: the caller's promise.
            SliceLoan::Shm(s) => Loaned::Shm(unsafe { s.assume_init() }),
            // SAFETY: the caller's promise.
            SliceLoan::Local(h, p) => Loaned::Local(h, unsafe { p.assume_init() }),
        }
    }
}
