//! Prompt timelines: a text per time span of a generated motion.

use crate::error::{Result, SampleError};

/// A prompt that applies from a frame on.
#[derive(Debug, Clone, PartialEq)]
pub struct Prompt {
    /// First frame (counted from the first generated frame).
    pub start_frame: usize,
    /// The text.
    pub text: String,
}

/// Reads a timeline: one prompt per line, `SECONDS TEXT` (the first at 0, increasing; blank
/// lines and lines starting with `#` are skipped).
pub fn parse_timeline(text: &str, fps: f32, source_name: &str) -> Result<Vec<Prompt>> {
    let mut prompts: Vec<Prompt> = Vec::new();
    for (n, line) in text.lines().enumerate() {
        let line = line.trim();
        if line.is_empty() || line.starts_with('#') {
            continue;
        }
        let bad = |expected: &str| {
            SampleError::invalid(source_name, format!("line {}", n + 1), expected, line)
        };
        let (seconds, prompt) =
            line.split_once(char::is_whitespace).ok_or_else(|| bad("SECONDS TEXT"))?;
        let seconds: f32 =
            seconds.parse().map_err(|_| bad("a start time in seconds, then the text"))?;
        if !(seconds >= 0.0 && seconds.is_finite()) {
            return Err(bad("a non-negative start time"));
        }
        let start_frame = (seconds * fps).round() as usize;
        if prompts.last().is_some_and(|p| p.start_frame >= start_frame) {
            return Err(bad("start times that increase"));
        }
        if prompts.is_empty() && start_frame != 0 {
            return Err(bad("the first prompt at 0 seconds"));
        }
        prompts.push(Prompt { start_frame, text: prompt.trim().to_string() });
    }
    if prompts.is_empty() {
        return Err(SampleError::invalid(source_name, "timeline", "at least one prompt", "none"));
    }
    Ok(prompts)
}
