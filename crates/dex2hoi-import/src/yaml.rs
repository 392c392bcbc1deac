//! The part of YAML that HUMOTO's per-sequence text files use: a top-level mapping of keys to
//! text (plain, single- or double-quoted scalars, folded over several lines, and `|` / `>`
//! block scalars, as PyYAML's `yaml.dump` writes them). Nested mappings and lists under a key
//! are skipped, not interpreted; only top-level text values are returned.

use std::collections::BTreeMap;

use crate::error::{ImportError, Result};

/// Reads the top-level text values of a YAML document. Keys whose value is a nested mapping
/// or list are left out.
pub fn top_level_text(text: &str, source_name: &str) -> Result<BTreeMap<String, String>> {
    let lines: Vec<&str> = text.lines().collect();
    let mut out = BTreeMap::new();
    let mut i = 0;
    while i < lines.len() {
        let line = lines[i];
        let trimmed = line.trim_end();
        i += 1;
        if trimmed.is_empty()
            || trimmed.starts_with('#')
            || trimmed == "---"
            || trimmed == "..."
            || line.starts_with([' ', '\t', '-'])
        {
            continue;
        }
        let (key, rest) = split_key(trimmed).ok_or_else(|| {
            ImportError::format(source_name, format!("line {i}"), "`key: value`", trimmed)
        })?;
        // The continuation lines of this key: everything more indented (or blank) that follows.
        let start = i;
        // PyYAML writes a list under a key without indenting it (`key:` then `- item`).
        let belongs = |l: &str| {
            l.trim().is_empty() || l.starts_with([' ', '\t']) || l == "-" || l.starts_with("- ")
        };
        while i < lines.len() && belongs(lines[i]) {
            i += 1;
        }
        let continuation = &lines[start..i];
        let rest = strip_comment(rest).trim();
        let value = if rest.is_empty() {
            // A nested mapping or list (or an empty value): not text.
            if continuation.iter().all(|l| l.trim().is_empty()) {
                Some(String::new())
            } else {
                None
            }
        } else if let Some(indicator) = rest.strip_prefix(['|', '>']) {
            let folded = rest.starts_with('>');
            Some(block_scalar(continuation, folded, indicator))
        } else if rest.starts_with('\'') || rest.starts_with('"') {
            let mut joined = rest.to_string();
            for l in continuation {
                joined.push('\n');
                joined.push_str(l.trim());
            }
            Some(quoted(&joined, source_name, &key)?)
        } else {
            let mut words = vec![rest.to_string()];
            words.extend(continuation.iter().map(|l| strip_comment(l).trim().to_string()));
            Some(fold_lines(&words))
        };
        if let Some(value) = value {
            out.insert(unquote_key(&key), value);
        }
    }
    Ok(out)
}

/// `key: rest` at the top level (a quoted key may hold a colon).
fn split_key(line: &str) -> Option<(String, &str)> {
    if line.starts_with(['\'', '"']) {
        let quote = line.chars().next()?;
        let close = line[1..].find(quote)? + 1;
        let rest = line[close + 1..].trim_start().strip_prefix(':')?;
        return Some((line[..=close].to_string(), rest));
    }
    let at = line.find(": ").or_else(|| line.strip_suffix(':').map(|s| s.len()))?;
    Some((line[..at].trim().to_string(), line.get(at + 1..).unwrap_or("")))
}

fn unquote_key(key: &str) -> String {
    key.trim_matches(['\'', '"']).to_string()
}

/// Removes a ` #` comment from a plain line (not inside quotes: only used on plain scalars).
fn strip_comment(text: &str) -> &str {
    if text.trim_start().starts_with(['\'', '"']) {
        return text;
    }
    match text.find(" #") {
        Some(at) => &text[..at],
        None => text,
    }
}

/// Joins the lines of a plain or quoted scalar: single line breaks become spaces, empty lines
/// become line breaks (YAML line folding).
fn fold_lines(lines: &[String]) -> String {
    let mut out = String::new();
    let mut pending_breaks = 0;
    for line in lines {
        if line.is_empty() {
            pending_breaks += 1;
            continue;
        }
        if !out.is_empty() {
            if pending_breaks > 0 {
                out.extend(std::iter::repeat_n('\n', pending_breaks));
            } else {
                out.push(' ');
            }
        }
        pending_breaks = 0;
        out.push_str(line);
    }
    out
}

/// A quoted scalar that may span lines: `'it''s'` or `"a \"b\"\n"`.
fn quoted(text: &str, source_name: &str, key: &str) -> Result<String> {
    let quote = text.chars().next().unwrap_or('"');
    let body = &text[1..];
    let mut raw = String::new();
    let mut chars = body.chars().peekable();
    let mut closed = false;
    while let Some(c) = chars.next() {
        if quote == '\'' && c == '\'' {
            if chars.peek() == Some(&'\'') {
                chars.next();
                raw.push('\'');
                continue;
            }
            closed = true;
            break;
        }
        if quote == '"' && c == '"' {
            closed = true;
            break;
        }
        if quote == '"' && c == '\\' {
            match chars.next() {
                Some('n') => raw.push('\u{1}'), // a kept line break, restored after folding
                Some('t') => raw.push('\t'),
                Some('"') => raw.push('"'),
                Some('\\') => raw.push('\\'),
                Some('/') => raw.push('/'),
                Some('\n') => {
                    // An escaped line break joins the lines without a space.
                    while chars.peek().is_some_and(|c| *c == ' ') {
                        chars.next();
                    }
                    raw.push('\u{2}');
                }
                Some('u') => {
                    let hex: String = chars.by_ref().take(4).collect();
                    let code = u32::from_str_radix(&hex, 16).ok().and_then(char::from_u32);
                    raw.push(code.unwrap_or('\u{fffd}'));
                }
                Some(other) => {
                    raw.push('\\');
                    raw.push(other);
                }
                None => {}
            }
            continue;
        }
        raw.push(c);
    }
    if !closed {
        return Err(ImportError::format(
            source_name,
            format!("value of `{key}`"),
            format!("a closing {quote}"),
            "the end of the text",
        ));
    }
    let lines: Vec<String> = raw.split('\n').map(|l| l.trim().to_string()).collect();
    Ok(fold_lines(&lines).replace("\u{2} ", "").replace('\u{2}', "").replace('\u{1}', "\n"))
}

/// A `|` (literal) or `>` (folded) block scalar with its chomping indicator (`-`, `+`).
fn block_scalar(lines: &[&str], folded: bool, indicator: &str) -> String {
    let indent = lines
        .iter()
        .filter(|l| !l.trim().is_empty())
        .map(|l| l.len() - l.trim_start().len())
        .min()
        .unwrap_or(0);
    let body: Vec<String> =
        lines.iter().map(|l| l.get(indent..).unwrap_or("").trim_end().to_string()).collect();
    let mut text = if folded { fold_lines(&body) } else { body.join("\n") };
    let text_end = text.trim_end_matches('\n').len();
    text.truncate(text_end);
    if indicator.contains('+') {
        let trailing = body.iter().rev().take_while(|l| l.is_empty()).count();
        text.extend(std::iter::repeat_n('\n', trailing + 1));
    } else if !indicator.contains('-') {
        text.push('\n');
    }
    text
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_scalars_pyyaml_writes() {
        let text = "\
# a comment
long_script: The person walks to the table, picks up the mug with the right hand and
  puts it on the shelf.
objects:
- mug
- shelf
quoted: 'It''s a: test'
double: \"line one\\nline two\"
short_script: pick up the mug  # trailing comment
block: |
  first
  second
folded: >-
  one
  two
";
        let values = top_level_text(text, "t.yaml").unwrap();
        assert_eq!(
            values["long_script"],
            "The person walks to the table, picks up the mug with the right hand and puts it on \
             the shelf."
        );
        assert_eq!(values["short_script"], "pick up the mug");
        assert_eq!(values["quoted"], "It's a: test");
        assert_eq!(values["double"], "line one\nline two");
        assert_eq!(values["block"], "first\nsecond\n");
        assert_eq!(values["folded"], "one two");
        assert!(!values.contains_key("objects"));
    }

    #[test]
    fn unclosed_quotes_are_errors() {
        let error = top_level_text("a: 'open\n", "t.yaml").unwrap_err().to_string();
        assert!(error.contains("t.yaml") && error.contains("`a`"), "{error}");
    }
}
