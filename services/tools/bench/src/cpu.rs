//! Per-thread CPU time, the measure of "producer CPU per frame" and "consumer CPU per frame".

/// CPU time consumed by the calling thread so far (user + system), ns:
/// `clock_gettime(CLOCK_THREAD_CPUTIME_ID)`. Time spent blocked (in `read`, `epoll_wait`, sleeping)
/// does not count; the kernel's work on the thread's behalf (copies in `write`/`read`) does.
pub fn thread_cpu_ns() -> u64 {
    let mut ts = libc::timespec { tv_sec: 0, tv_nsec: 0 };
    // SAFETY: ts is a valid, writable timespec; CLOCK_THREAD_CPUTIME_ID always exists on Linux.
    unsafe { libc::clock_gettime(libc::CLOCK_THREAD_CPUTIME_ID, &mut ts) };
    ts.tv_sec as u64 * 1_000_000_000 + ts.tv_nsec as u64
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn thread_cpu_time_advances_with_work() {
        let a = thread_cpu_ns();
        let mut x = 0u64;
        for i in 0..5_000_000u64 {
            x = std::hint::black_box(x.wrapping_mul(31).wrapping_add(i));
        }
        let b = thread_cpu_ns();
        assert!(b > a, "{x}");
    }
}
