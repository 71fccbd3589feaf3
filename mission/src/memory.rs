//! The process's own memory, as Linux counts it: what an operator sizing the base station's
//! machine needs from a run (the model server's peak in `summary.json` and the report) and
//! what `fleet bench epoch` reports at each grid size.

/// The process's peak resident size so far (kB; Linux's `VmHWM`), or `None` where there is no
/// `/proc` to read it from.
pub fn peak_resident_kb() -> Option<u64> {
    let status = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = status.lines().find(|l| l.starts_with("VmHWM:"))?;
    line.split_whitespace().nth(1)?.parse().ok()
}

/// [`peak_resident_kb`] in MiB, as the server's summary and report give it.
pub fn peak_resident_mib() -> Option<f64> {
    peak_resident_kb().map(|kb| kb as f64 / 1024.0)
}

/// mimalloc's own setting for transparent huge pages (`0` turns them off for the process,
/// `1` leaves them on): a value set there is the user's choice, and [`small_pages_only`] keeps
/// it.
pub const ALLOW_THP: &str = "MIMALLOC_ALLOW_THP";

/// Whether this process takes transparent huge pages, and why.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum HugePages {
    /// Turned off here (`prctl(PR_SET_THP_DISABLE)`).
    Off,
    /// Left to [`ALLOW_THP`], which the user set.
    AsSet,
    /// The kernel refused the request (the process keeps its pages as they were).
    Refused,
}

/// Transparent huge pages off for this process, unless [`ALLOW_THP`] is set. Call once at
/// start-up, before the big allocations.
///
/// Why: mimalloc marks its arenas `MADV_HUGEPAGE`, and a kernel whose `defrag` is `madvise`
/// (this machine's, and the default of many distributions) then compacts memory at the fault
/// to find a 2 MB page. The model server's heap grows over its first epochs, so those epochs
/// took 2 MB faults and stalled: at 384 x 768 the first epoch's model came out in 724-743 ms
/// with them and 541-557 ms without, the median unchanged (docs/decisions/082).
pub fn small_pages_only() -> HugePages {
    if std::env::var_os(ALLOW_THP).is_some() {
        return HugePages::AsSet;
    }
    // SAFETY: PR_SET_THP_DISABLE reads its integer arguments and sets a flag of this process.
    match unsafe { libc::prctl(libc::PR_SET_THP_DISABLE, 1, 0, 0, 0) } {
        0 => HugePages::Off,
        _ => HugePages::Refused,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The process's resident size now (kB; `VmRSS`).
    fn resident_kb() -> u64 {
        let status = std::fs::read_to_string("/proc/self/status").unwrap();
        let line = status.lines().find(|l| l.starts_with("VmRSS:")).unwrap();
        line.split_whitespace().nth(1).unwrap().parse().unwrap()
    }

    /// After [`small_pages_only`] the kernel says this process takes no transparent huge pages
    /// (`THP_enabled: 0` in its status; 1 before, on a kernel that offers them), unless the
    /// user set mimalloc's own switch, which is then left alone.
    #[test]
    fn huge_pages_are_off_unless_the_user_chose() {
        let thp = || {
            let status = std::fs::read_to_string("/proc/self/status").unwrap();
            let line = status
                .lines()
                .find(|l| l.starts_with("THP_enabled:"))
                .map(str::to_owned);
            line.and_then(|l| l.split_whitespace().nth(1).map(str::to_owned))
        };
        let before = thp();
        let got = small_pages_only();
        match std::env::var_os(ALLOW_THP) {
            Some(_) => assert_eq!((got, thp()), (HugePages::AsSet, before)),
            None => {
                assert_eq!(got, HugePages::Off);
                // A kernel without THP_enabled in the status (older than 5.0) cannot be asked.
                if before.is_some() {
                    assert_eq!(thp().as_deref(), Some("0"));
                }
            }
        }
    }

    /// The peak sees memory this process touched: 128 MB written on top of what is resident now
    /// put the peak at least 96 MB above it (the margin for what tests on other threads free
    /// meanwhile).
    #[test]
    fn the_peak_sees_memory_touched() {
        let now = resident_kb();
        let touched = vec![1u8; 128 << 20];
        std::hint::black_box(&touched);
        let peak = peak_resident_kb().expect("VmHWM on Linux");
        assert!(peak >= now + (96 << 10), "resident {now} kB, then a peak of {peak} kB");
    }
}
