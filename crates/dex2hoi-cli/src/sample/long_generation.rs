//! What makes a long `dex2hoi sample` behave: a length whose motion and exports would not fit
//! in memory is refused before any work, a long generation says how long it will take and
//! shows its progress, and Ctrl-C stops it between windows with nothing written.

use std::ops::ControlFlow;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

use anyhow::{Context, Result, bail};
use indicatif::{ProgressBar, ProgressDrawTarget, ProgressStyle};

use dex2hoi_sample::{ProgressHook, WindowProgress};

/// Bytes of one `f32`.
const F32: u64 = 4;
/// Bytes of a 3 x 3 rotation matrix of `f32` (`glam::Mat3`).
const MAT3: u64 = 9 * F32;
/// Bytes of a position (`glam::Vec3`).
const VEC3: u64 = 3 * F32;
/// Copies of the generated features alive at once: the windows, their concatenation, its
/// denormalised copy and the flattened vector, then the body and object split for decoding.
const FEATURE_COPIES: u64 = 5;
/// A growing output buffer (`Vec<u8>`) can hold up to twice what it contains.
const GROWTH: u64 = 2;
/// Rows of the preview's caption band: 48 with the built-in font at its scale; the rest is
/// room so that the estimate stays above what is used.
const CAPTION_ROWS: u64 = 64;
/// Bytes of a GIF frame per raw preview frame: the LZW-coded GIF of a rendered motion is about
/// 5% of its palette indices (10.7 kB a frame for 235 kB); a quarter leaves room for busier
/// pictures and the encoder's growing buffer.
const GIF_PER_RAW: u64 = 4;
/// What a `sample` process holds whatever the length: the binary, the model, the object meshes
/// and BPS, the allocator's slack (about 41 MB measured with the shipped model).
pub const FIXED_BYTES: u64 = 128 << 20;
/// Memory assumed available where the operating system does not say (no `/proc/meminfo`):
/// 4 GiB, what a small laptop can spare.
pub const FALLBACK_AVAILABLE: u64 = 4 << 30;
/// Generations expected to take less than this run without an estimate or a progress bar.
const LONG_GENERATION: Duration = Duration::from_secs(3);

/// What a generated frame costs in memory until `sample` has written its outputs: the one
/// source of truth for the length check. The terms, per frame:
///
/// - the features of both streams, `[2, frames, D]` f32, in [`FEATURE_COPIES`] copies;
/// - the decoded motion: local rotations and root position, FK joint rotations and positions,
///   and a rotation and a position per object;
/// - the exports' encodings, each in a buffer that may have grown to twice its size: the npz
///   (the decoded arrays again), the glb (a rotation and a translation per joint) and the bvh
///   (about 32 characters per joint);
/// - the preview: every frame rendered, two views side by side with the caption above (one
///   palette byte a pixel), and its GIF.
///
/// With the shipped model (52 joints, D = 333) and the default preview that is 327 kB a frame;
/// measured peaks grow by 273 kB a frame (40 to 1200 frames).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct FrameCost {
    /// Features per stream and frame (`D`).
    pub stream_features: usize,
    /// Joints of the skeleton.
    pub joints: usize,
    /// Objects in the scene.
    pub objects: usize,
    /// Width of one preview view in pixels.
    pub preview_width: u32,
    /// Height of one preview view in pixels (without the caption).
    pub preview_height: u32,
}

impl FrameCost {
    /// Bytes held per generated frame (see the type's docs).
    pub fn bytes(&self) -> u64 {
        let (d, joints, objects) =
            (self.stream_features as u64, self.joints as u64, self.objects as u64);
        let features = FEATURE_COPIES * 2 * d * F32;
        let decoded = joints * (MAT3 + MAT3 + VEC3) + VEC3 + objects * (MAT3 + VEC3);
        let npz = GROWTH * decoded;
        let glb = GROWTH * joints * (4 * F32 + VEC3);
        let bvh = GROWTH * joints * 32;
        let raw_preview =
            2 * u64::from(self.preview_width) * (u64::from(self.preview_height) + CAPTION_ROWS);
        let preview = raw_preview + raw_preview / GIF_PER_RAW;
        features + decoded + npz + glb + bvh + preview
    }

    /// Bytes a generation of `frames` frames needs in all, [`FIXED_BYTES`] included
    /// (saturating: a length this large is refused anyway).
    pub fn total(&self, frames: usize) -> u64 {
        (frames as u64).saturating_mul(self.bytes()).saturating_add(FIXED_BYTES)
    }

    /// The most frames whose generation fits in `available` bytes (0 when none does).
    pub fn max_frames(&self, available: u64) -> u64 {
        available.saturating_sub(FIXED_BYTES) / self.bytes().max(1)
    }
}

/// Memory the machine can give a process, and where the number comes from.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct AvailableMemory {
    /// Bytes.
    pub bytes: u64,
    /// Where the number comes from, for messages.
    pub source: &'static str,
}

impl AvailableMemory {
    /// `MemAvailable` of `/proc/meminfo` (Linux), else [`FALLBACK_AVAILABLE`].
    pub fn of_this_machine() -> Self {
        std::fs::read_to_string("/proc/meminfo").ok().and_then(|text| mem_available(&text)).map_or(
            Self { bytes: FALLBACK_AVAILABLE, source: "a fixed ceiling: this system does not say" },
            |bytes| Self { bytes, source: "MemAvailable in /proc/meminfo" },
        )
    }
}

/// The `MemAvailable` line of a `/proc/meminfo` text, in bytes.
fn mem_available(meminfo: &str) -> Option<u64> {
    let line = meminfo.lines().find_map(|l| l.strip_prefix("MemAvailable:"))?;
    let mut words = line.split_whitespace();
    let value: u64 = words.next()?.parse().ok()?;
    match words.next() {
        Some("kB") => value.checked_mul(1024),
        None => Some(value),
        Some(_) => None,
    }
}

/// Refuses a length whose generation would not fit in `available`, with an error that names
/// `--frames`, the length in frames and time, the memory it needs and has, and the most that
/// fits.
pub fn check_length(
    frames: usize,
    fps: f32,
    cost: &FrameCost,
    available: &AvailableMemory,
) -> Result<()> {
    let needed = cost.total(frames);
    if needed <= available.bytes {
        return Ok(());
    }
    let most = cost.max_frames(available.bytes);
    let fitting = if most == 0 {
        "not even one frame fits".to_owned()
    } else {
        format!(
            "at most --frames {most} ({} of motion) fits",
            duration_words(most as f64 / f64::from(fps))
        )
    };
    bail!(
        "--frames {frames} ({} of motion at {fps} fps) would need about {} of memory for the \
         motion and its exports ({} a frame), but {} is available ({}); {fitting}",
        duration_words(frames as f64 / f64::from(fps)),
        bytes_words(needed),
        bytes_words(cost.bytes()),
        bytes_words(available.bytes),
        available.source,
    )
}

/// A length of time in words: `4.2 s`, `100 s`, `1 min 10 s`, `3 h 5 min`, `58 days`.
pub fn duration_words(seconds: f64) -> String {
    if !seconds.is_finite() || seconds < 0.0 {
        return "an unknown time".to_owned();
    }
    if seconds < 10.0 {
        return format!("{seconds:.1} s");
    }
    let whole = seconds.round() as u64;
    let (minutes, hours, days) = (whole / 60, whole / 3600, whole / 86_400);
    match whole {
        0..120 => format!("{whole} s"),
        120..7200 if whole.is_multiple_of(60) => format!("{minutes} min"),
        120..7200 => format!("{minutes} min {} s", whole % 60),
        7200..172_800 => format!("{hours} h {} min", (whole % 3600) / 60),
        _ => format!("{} days", (seconds / 86_400.0).round().max(days as f64)),
    }
}

/// A number of bytes in words (binary units): `512 B`, `3.4 MiB`, `29.7 TiB`.
pub fn bytes_words(bytes: u64) -> String {
    const UNITS: [&str; 6] = ["B", "KiB", "MiB", "GiB", "TiB", "PiB"];
    let mut value = bytes as f64;
    let mut unit = 0;
    while value >= 1024.0 && unit + 1 < UNITS.len() {
        value /= 1024.0;
        unit += 1;
    }
    if unit == 0 { format!("{bytes} B") } else { format!("{value:.1} {}", UNITS[unit]) }
}

/// What the progress of a generation is reported with.
#[derive(Debug, Clone, Copy)]
pub struct GenerationShape {
    /// Frames per second of the run.
    pub fps: f32,
    /// Frames each window adds (`predicted_frames`).
    pub window_frames: usize,
    /// Denoising steps per window.
    pub steps: usize,
}

/// Watches a generation: after its first window, announces the estimated time and shows a
/// progress bar when it will take more than a few seconds; stops it at the next window once
/// Ctrl-C has been pressed.
#[derive(Debug)]
pub struct GenerationWatch {
    started: Instant,
    bar: ProgressBar,
    shape: GenerationShape,
    stop: Arc<AtomicBool>,
}

impl GenerationWatch {
    /// A watch started now, stopping when `stop` is set.
    pub fn start(shape: GenerationShape, stop: Arc<AtomicBool>) -> Result<Self> {
        // Hidden until the first window shows that the generation is long.
        let bar = ProgressBar::with_draw_target(None, ProgressDrawTarget::hidden());
        bar.set_style(
            ProgressStyle::with_template(
                "{spinner} generating [{bar:30}] {pos}/{len} windows, {elapsed} elapsed, eta {eta}",
            )
            .context("progress bar template")?
            .progress_chars("=> "),
        );
        Ok(Self { started: Instant::now(), bar, shape, stop })
    }

    /// The hook the generation calls after each window.
    pub fn hook(self: &Arc<Self>) -> ProgressHook {
        let watch = Arc::clone(self);
        ProgressHook::new(move |progress| watch.window_done(progress))
    }

    fn window_done(&self, progress: WindowProgress) -> ControlFlow<()> {
        if self.stop.load(Ordering::SeqCst) {
            return ControlFlow::Break(());
        }
        if progress.windows_done == 1 && progress.windows > 1 {
            let first = self.started.elapsed();
            let expected =
                first.saturating_mul(u32::try_from(progress.windows).unwrap_or(u32::MAX));
            if expected >= LONG_GENERATION {
                let fps = f64::from(self.shape.fps);
                eprintln!(
                    "generating {} frames ({} of motion) in {} windows of {} frames with {} \
                     denoising steps, about {} (the first window took {})",
                    progress.frames,
                    duration_words(progress.frames as f64 / fps),
                    progress.windows,
                    self.shape.window_frames,
                    self.shape.steps,
                    duration_words(expected.as_secs_f64()),
                    duration_words(first.as_secs_f64()),
                );
                self.bar.set_length(progress.windows as u64);
                // Drawn only where stderr is a terminal, as the other commands' bars.
                self.bar.set_draw_target(ProgressDrawTarget::stderr());
                // Windows can take seconds each: keep the elapsed time moving between them.
                self.bar.enable_steady_tick(Duration::from_millis(200));
            }
        }
        self.bar.set_position(progress.windows_done as u64);
        ControlFlow::Continue(())
    }

    /// Whether the generation was long enough to be announced.
    pub fn was_announced(&self) -> bool {
        self.bar.length().is_some()
    }

    /// Removes the progress bar.
    pub fn finish(&self) {
        self.bar.finish_and_clear();
    }
}

/// Installs the Ctrl-C handler of `sample`. While `generating` is set, the first Ctrl-C sets
/// the returned flag (the generation stops at its next window and nothing is written) and a
/// second leaves at once; outside the generation (loading, rendering and writing the outputs,
/// each file written whole or not at all) Ctrl-C leaves at once.
pub fn install_ctrl_c(generating: Arc<AtomicBool>) -> Result<Arc<AtomicBool>> {
    let stop = Arc::new(AtomicBool::new(false));
    let flag = Arc::clone(&stop);
    ctrlc::set_handler(move || {
        if !generating.load(Ordering::SeqCst) {
            eprintln!("\nCtrl-C: leaving");
            std::process::exit(130);
        }
        if flag.swap(true, Ordering::SeqCst) {
            eprintln!("\nsecond Ctrl-C: leaving at once");
            std::process::exit(130);
        }
        eprintln!("\nCtrl-C: stopping after this window; nothing will be written");
    })
    .context("installing the Ctrl-C handler")?;
    Ok(stop)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The shipped model's sizes with the default preview.
    fn shipped() -> FrameCost {
        FrameCost {
            stream_features: 333,
            joints: 52,
            objects: 1,
            preview_width: 320,
            preview_height: 320,
        }
    }

    #[test]
    fn the_estimate_covers_what_a_frame_was_measured_to_take() {
        let bytes = shipped().bytes();
        // Peaks measured at 40 and 1200 frames grew by 273 kB a frame; the estimate stays
        // above that without refusing lengths that fit by a wide margin.
        assert!((273_000..400_000).contains(&bytes), "{bytes}");
        // The preview dominates: a larger picture costs more, another object a little.
        let large = FrameCost { preview_width: 640, preview_height: 640, ..shipped() };
        assert!(large.bytes() > 3 * bytes);
        let two = FrameCost { objects: 2, ..shipped() };
        assert!(two.bytes() > bytes && two.bytes() < bytes + 1000);
    }

    #[test]
    fn lengths_are_checked_against_the_memory_available() {
        let cost = shipped();
        let available = AvailableMemory { bytes: 16 << 30, source: "a test" };
        assert!(check_length(2000, 20.0, &cost, &available).is_ok());
        let most = cost.max_frames(available.bytes);
        assert!(cost.total(most as usize) <= available.bytes);
        assert!(cost.total(most as usize + 1) > available.bytes);
        assert!(check_length(most as usize, 20.0, &cost, &available).is_ok());
        let error = check_length(100_000_000, 20.0, &cost, &available).unwrap_err().to_string();
        for needle in ["--frames 100000000", "58 days", "TiB", "16.0 GiB is available", "a test"] {
            assert!(error.contains(needle), "`{needle}` in: {error}");
        }
        assert!(error.contains(&format!("at most --frames {most} (")), "{error}");
        // Nothing fits: said so, and no overflow on the largest length there is.
        let none = AvailableMemory { bytes: 1 << 20, source: "a test" };
        let error = check_length(usize::MAX, 20.0, &cost, &none).unwrap_err().to_string();
        assert!(error.contains("not even one frame fits"), "{error}");
    }

    #[test]
    fn meminfo_is_read_in_kilobytes() {
        let text = "MemTotal:       24000000 kB\nMemFree:  1 kB\nMemAvailable:   23000000 kB\n";
        assert_eq!(mem_available(text), Some(23_000_000 * 1024));
        assert_eq!(mem_available("MemTotal: 5 kB\n"), None);
        assert_eq!(mem_available("MemAvailable: lots\n"), None);
        let here = AvailableMemory::of_this_machine();
        assert!(here.bytes > 0);
    }

    #[test]
    fn durations_and_sizes_read_as_words() {
        assert_eq!(duration_words(4.24), "4.2 s");
        assert_eq!(duration_words(100.0), "100 s");
        assert_eq!(duration_words(130.0), "2 min 10 s");
        assert_eq!(duration_words(600.0), "10 min");
        assert_eq!(duration_words(3.0 * 3600.0 + 300.0), "3 h 5 min");
        assert_eq!(duration_words(100_000_000.0 / 20.0), "58 days");
        assert_eq!(duration_words(f64::NAN), "an unknown time");
        assert_eq!(bytes_words(512), "512 B");
        assert_eq!(bytes_words(3 << 20), "3.0 MiB");
        assert_eq!(bytes_words(u64::MAX), "16384.0 PiB");
    }
}
