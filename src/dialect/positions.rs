//! Where a program's values sit, and new values written there: in = a program text and the
//! byte ranges its reader recorded ([`Positions`]); out = [`Edit`]s a dialect's writer makes of
//! them, and the text with the edits applied ([`apply`]).
//!
//! A reader records the range of every value it parsed that a writer may replace: each move's
//! axis values, its time word and speed percentage, and where the language keeps header
//! comments and line numbers. A writer then changes those ranges and nothing else, so a
//! rewritten program is the same text around its new values, and no second tokenizer has to
//! agree with the reader about where a value is.

use super::ParseError;
use std::ops::Range;

/// Where one move's values sit in the text (byte ranges into the whole text).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct MoveSpans {
    /// The move's line (1-based).
    pub line: usize,
    /// The text that states the move's axis values, as the language groups it: one range per
    /// axis word the line writes (RS274 `X1.5`, SINUMERIK `X1=1.5`, in text order), one range
    /// per axis number (FANUC's `J1 = 1.500 deg` in `/POS`, axes 1..6), or one range for the
    /// whole list (KRL's `{A1 …}`, RAPID's robax `[…]`, URScript's `[…]`). Empty when the
    /// move names a variable the language does not let a writer replace.
    pub axes: Vec<Range<usize>>,
    /// The number of the move's time word (G93 F, `\T`, `t=`, `sec`), when the line writes one.
    pub time: Option<Range<usize>>,
    /// One second in the time word's unit (1 for s, 1000 for ms).
    pub time_per_s: f64,
    /// The number of the move's speed percentage (FANUC `n%`), when the line writes one.
    pub percent: Option<Range<usize>>,
    /// The move's whole line, without its line break.
    pub line_range: Range<usize>,
}

/// What a reader records besides the motions: where each value sits.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Positions {
    /// One per move, in the order of the moves in [`super::Parsed::lines`].
    pub moves: Vec<MoveSpans>,
    /// Where a header comment line may be inserted: the byte offset of a line's start (or the
    /// text's end).
    pub header_at: Option<usize>,
    /// The language's own line numbers (FANUC `/MN`: the indent and the number before `:`),
    /// with their values, in text order.
    pub line_numbers: Vec<(Range<usize>, usize)>,
    /// The line that states the number of lines (FANUC `LINE_COUNT = n;`), with the number.
    pub line_count: Option<(Range<usize>, usize)>,
    /// Why the text cannot take new values in place (RS274 G91: the values are increments),
    /// with its line.
    pub unwritable: Option<ParseError>,
}

/// The new values of one move, as its writer prints them.
#[derive(Clone, Debug, PartialEq)]
pub struct NewValues {
    /// The six axis values, printed.
    pub axes: [String; 6],
    /// The new time (s), when it changes.
    pub time: Option<f64>,
    /// The new axis speed percentages (KRL `$VEL_AXIS`, FANUC `n%`), when they change.
    pub percent: Option<[f64; 6]>,
    /// The percentages in force before (KRL restores them after the move).
    pub old_percent: [f64; 6],
}

/// One change of the text: `range` replaced by `with` (an empty range inserts).
#[derive(Clone, Debug, PartialEq)]
pub struct Edit {
    pub range: Range<usize>,
    pub with: String,
}

impl Edit {
    pub fn replace(range: Range<usize>, with: impl Into<String>) -> Edit {
        Edit {
            range,
            with: with.into(),
        }
    }

    pub fn insert(at: usize, with: impl Into<String>) -> Edit {
        Edit::replace(at..at, with)
    }
}

/// Why a writer cannot put the new values into the text, with the line.
#[derive(Debug, thiserror::Error, PartialEq, Clone)]
#[error("line {line}: {msg}")]
pub struct WriteError {
    pub line: usize,
    pub msg: String,
}

pub(crate) fn werr(line: usize, msg: impl Into<String>) -> WriteError {
    WriteError {
        line,
        msg: msg.into(),
    }
}

/// The text with the edits applied. Edits are taken in text order; insertions at one place
/// keep the order they are given in and come before a replacement that starts there; of two
/// edits of the same range the later one wins. Overlapping edits are a writer's error.
pub fn apply(text: &str, edits: &[Edit]) -> Result<String, WriteError> {
    let mut order: Vec<&Edit> = edits.iter().collect();
    order.sort_by_key(|e| (e.range.start, e.range.end));
    let mut out = String::with_capacity(text.len() + 256);
    let mut at = 0;
    for (k, e) in order.iter().enumerate() {
        let replaced_later = order
            .get(k + 1)
            .is_some_and(|n| !e.range.is_empty() && n.range == e.range);
        if replaced_later {
            continue;
        }
        if e.range.start < at || e.range.end > text.len() {
            return Err(werr(0, "overlapping edits of the program text"));
        }
        out.push_str(&text[at..e.range.start]);
        out.push_str(&e.with);
        at = e.range.end;
    }
    out.push_str(&text[at..]);
    Ok(out)
}

/// The byte offset of `inner`, a slice of `outer`, in `outer`.
pub(crate) fn offset_in(outer: &str, inner: &str) -> usize {
    let o = (inner.as_ptr() as usize).wrapping_sub(outer.as_ptr() as usize);
    assert!(
        o <= outer.len() && o + inner.len() <= outer.len(),
        "not a slice of the text"
    );
    o
}

/// The byte range of `inner`, a slice of `outer`, in `outer`.
pub(crate) fn span(outer: &str, inner: &str) -> Range<usize> {
    let o = offset_in(outer, inner);
    o..o + inner.len()
}

/// The range `r` of a string that starts at byte `base` of the text.
pub(crate) fn shifted(base: usize, r: Range<usize>) -> Range<usize> {
    base + r.start..base + r.end
}

/// The byte offset where the line after the one in `line` (a slice of `text`) starts: after
/// its line break, or the text's end.
pub(crate) fn after_line(text: &str, line: &str) -> usize {
    let end = offset_in(text, line) + line.len();
    match text[end..].find('\n') {
        Some(k) => end + k + 1,
        None => text.len(),
    }
}

/// Edits that write `full` (all six axis words) at the place of the first of a line's axis
/// `words` and remove the others, each with the space before it: a G-code move may name only
/// the axes that change, and a compensated one changes them all.
pub(crate) fn words_replaced(
    text: &str,
    words: &[Range<usize>],
    full: &str,
    line: usize,
) -> Result<Vec<Edit>, WriteError> {
    let first = words
        .first()
        .ok_or_else(|| werr(line, "no axis words on the move's line"))?;
    let mut out = vec![Edit::replace(first.clone(), full)];
    for w in &words[1..] {
        let start = if w.start > 0 && text.as_bytes()[w.start - 1] == b' ' {
            w.start - 1
        } else {
            w.start
        };
        out.push(Edit::replace(start..w.end, ""));
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn edits_apply_in_text_order() {
        let t = "abc def ghi";
        let e = [
            Edit::replace(4..7, "XY"),
            Edit::insert(0, "1"),
            Edit::replace(8..11, "old"),
            Edit::insert(0, "2"),
            Edit::replace(8..11, "new"),
            Edit::replace(0..3, "A"),
        ];
        assert_eq!(apply(t, &e).unwrap(), "12A XY new");
        assert!(apply(t, &[Edit::replace(0..5, ""), Edit::replace(4..6, "")]).is_err());
        let line = t.lines().next().unwrap();
        assert_eq!(after_line(t, line), t.len());
        assert_eq!(span(t, &t[4..7]), 4..7);
    }
}
