//! The project's bitmap font: 3 x 5 pixel capitals, digits and the punctuation of prompts, for
//! the preview's captions and the training plots. No font files, no dependencies, the same
//! pixels everywhere.

/// Glyph width and height in font pixels, and the advance per character (one column of space).
pub const GLYPH_WIDTH: usize = 3;
/// See [`GLYPH_WIDTH`].
pub const GLYPH_HEIGHT: usize = 5;
/// See [`GLYPH_WIDTH`].
pub const ADVANCE: usize = 4;

/// A character's rows, top to bottom, three bits per row (the leftmost is the high bit); letters
/// are drawn as capitals, anything unknown is blank.
pub fn glyph(c: char) -> [u8; 5] {
    match c.to_ascii_lowercase() {
        'a' => [2, 5, 7, 5, 5],
        'b' => [6, 5, 6, 5, 6],
        'c' => [3, 4, 4, 4, 3],
        'd' => [6, 5, 5, 5, 6],
        'e' => [7, 4, 6, 4, 7],
        'f' => [7, 4, 6, 4, 4],
        'g' => [3, 4, 5, 5, 3],
        'h' => [5, 5, 7, 5, 5],
        'i' => [7, 2, 2, 2, 7],
        'j' => [1, 1, 1, 5, 2],
        'k' => [5, 5, 6, 5, 5],
        'l' => [4, 4, 4, 4, 7],
        'm' => [5, 7, 7, 5, 5],
        'n' => [6, 5, 5, 5, 5],
        'o' => [2, 5, 5, 5, 2],
        'p' => [6, 5, 6, 4, 4],
        'q' => [2, 5, 5, 6, 3],
        'r' => [6, 5, 6, 5, 5],
        's' => [3, 4, 2, 1, 6],
        't' => [7, 2, 2, 2, 2],
        'u' => [5, 5, 5, 5, 7],
        'v' => [5, 5, 5, 5, 2],
        'w' => [5, 5, 7, 7, 5],
        'x' => [5, 5, 2, 5, 5],
        'y' => [5, 5, 2, 2, 2],
        'z' => [7, 1, 2, 4, 7],
        '0' => [7, 5, 5, 5, 7],
        '1' => [2, 6, 2, 2, 7],
        '2' => [6, 1, 2, 4, 7],
        '3' => [6, 1, 2, 1, 6],
        '4' => [5, 5, 7, 1, 1],
        '5' => [7, 4, 6, 1, 6],
        '6' => [3, 4, 7, 5, 7],
        '7' => [7, 1, 2, 2, 2],
        '8' => [7, 5, 7, 5, 7],
        '9' => [7, 5, 7, 1, 6],
        '.' => [0, 0, 0, 0, 2],
        ',' => [0, 0, 0, 2, 4],
        '\'' => [2, 2, 0, 0, 0],
        '"' => [5, 5, 0, 0, 0],
        '!' => [2, 2, 2, 0, 2],
        '?' => [6, 1, 2, 0, 2],
        '-' => [0, 0, 7, 0, 0],
        '_' => [0, 0, 0, 0, 7],
        '+' => [0, 2, 7, 2, 0],
        '=' => [0, 7, 0, 7, 0],
        '/' => [1, 1, 2, 4, 4],
        '|' => [2, 2, 2, 2, 2],
        '(' => [1, 2, 2, 2, 1],
        ')' => [4, 2, 2, 2, 4],
        '%' => [5, 1, 2, 4, 5],
        '>' => [4, 2, 1, 2, 4],
        '<' => [1, 2, 4, 2, 1],
        ':' => [0, 2, 0, 2, 0],
        ';' => [0, 2, 0, 2, 4],
        _ => [0; 5],
    }
}

/// Width in pixels of `text` drawn at `scale` (no trailing space).
pub fn text_width(text: &str, scale: usize) -> usize {
    (text.chars().count() * ADVANCE).saturating_sub(ADVANCE - GLYPH_WIDTH) * scale
}

/// Calls `set(x, y)` for every pixel of `text` drawn at `scale` with its top-left corner at
/// `(x, y)`; pixels may fall outside the caller's image (it clips).
pub fn draw_text(x: usize, y: usize, text: &str, scale: usize, mut set: impl FnMut(usize, usize)) {
    for (n, c) in text.chars().enumerate() {
        for (row, bits) in glyph(c).iter().enumerate() {
            for column in 0..GLYPH_WIDTH {
                if bits & (4 >> column) == 0 {
                    continue;
                }
                for dy in 0..scale {
                    for dx in 0..scale {
                        set(x + (n * ADVANCE + column) * scale + dx, y + row * scale + dy);
                    }
                }
            }
        }
    }
}

/// `text` broken at spaces into at most `max_lines` lines of at most `columns` characters; a
/// text that does not fit ends its last line with `...`.
pub fn wrap(text: &str, columns: usize, max_lines: usize) -> Vec<String> {
    let columns = columns.max(4);
    let mut lines: Vec<String> = Vec::new();
    let mut current = String::new();
    for word in text.split_whitespace() {
        let mut word = word.to_string();
        while word.chars().count() > columns {
            // A word longer than a line is cut.
            let head: String = word.chars().take(columns).collect();
            if !current.is_empty() {
                lines.push(std::mem::take(&mut current));
            }
            lines.push(head);
            word = word.chars().skip(columns).collect();
        }
        let needed =
            current.chars().count() + usize::from(!current.is_empty()) + word.chars().count();
        if needed > columns && !current.is_empty() {
            lines.push(std::mem::take(&mut current));
        }
        if !current.is_empty() {
            current.push(' ');
        }
        current.push_str(&word);
    }
    if !current.is_empty() {
        lines.push(current);
    }
    if lines.len() > max_lines {
        lines.truncate(max_lines);
        let last = &mut lines[max_lines - 1];
        let keep = last.chars().count().min(columns - 3);
        *last = last.chars().take(keep).collect::<String>() + "...";
    }
    lines
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn wrapping_keeps_words_and_marks_what_is_cut() {
        assert_eq!(wrap("The person lifts the mug.", 12, 3), ["The person", "lifts the", "mug."]);
        assert_eq!(wrap("one two three four", 8, 1), ["one t..."]);
        assert_eq!(wrap("abcdefghij", 4, 5), ["abcd", "efgh", "ij"]);
        assert!(wrap("   ", 10, 2).is_empty());
    }

    #[test]
    fn text_is_drawn_where_its_width_says() {
        let mut right = 0;
        draw_text(0, 0, "Hi, 2! 0", 2, |x, y| {
            assert!(y < GLYPH_HEIGHT * 2);
            right = right.max(x + 1);
        });
        assert_eq!(right, text_width("Hi, 2! 0", 2));
        assert_eq!(glyph('A'), glyph('a'));
        assert_eq!(glyph('\u{e9}'), [0; 5]);
    }
}
