//! Timelines: entries that each apply from a start frame on (a motion's prompts, in order of
//! their start frames), and which one is in force at a frame.

/// The last of `entries` (in order of their start frames) whose start is at or before `frame`;
/// `None` when every entry starts later.
pub fn in_force<T>(entries: &[T], start_frame: impl Fn(&T) -> usize, frame: usize) -> Option<&T> {
    entries.iter().rev().find(|entry| start_frame(entry) <= frame)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_latest_start_at_or_before_the_frame_is_in_force() {
        let prompts = [(0, "first"), (10, "second"), (25, "third")];
        let at = |frame| in_force(&prompts, |p| p.0, frame).map(|p| p.1);
        assert_eq!(
            [at(0), at(9), at(10), at(24), at(25), at(99)].map(Option::unwrap),
            ["first", "first", "second", "second", "third", "third"]
        );
        let late = [(5, "late")];
        assert_eq!(in_force(&late, |p| p.0, 4), None);
    }
}
