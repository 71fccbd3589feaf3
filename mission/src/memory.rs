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

#[cfg(test)]
mod tests {
    use super::*;

    /// The process's resident size now (kB; `VmRSS`).
    fn resident_kb() -> u64 {
        let status = std::fs::read_to_string("/proc/self/status").unwrap();
        let line = status.lines().find(|l| l.starts_with("VmRSS:")).unwrap();
        line.split_whitespace().nth(1).unwrap().parse().unwrap()
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
