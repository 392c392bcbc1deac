//! Peak resident memory of a benchmark process (the sampling and training benchmarks report
//! it beside their times).

/// Starts a new peak of the resident memory (Linux: `/proc/self/clear_refs`; elsewhere the
/// peak is the process's).
pub fn reset_peak_memory() {
    let _ = std::fs::write("/proc/self/clear_refs", "5");
}

/// The peak resident memory since the last reset, in MiB (`VmHWM`; 0 where unknown).
pub fn peak_memory_mib() -> f64 {
    let status = std::fs::read_to_string("/proc/self/status").unwrap_or_default();
    status
        .lines()
        .find_map(|line| line.strip_prefix("VmHWM:"))
        .and_then(|v| v.trim().trim_end_matches("kB").trim().parse::<f64>().ok())
        .map_or(0.0, |kib| kib / 1024.0)
}
