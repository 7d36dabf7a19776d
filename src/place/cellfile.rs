//! The cell file for a chosen fixture position: in = the user's cell text (or none), the
//! position, the settings the placement used that the text does not carry (flags, an assumed
//! stand), a comment block; out = cell TOML text that the compiler reads (`--cell`) to compile
//! exactly what the placement estimated. Edits with `toml_edit`, so the user's comments,
//! environment, tool and every other key stay as they were.

use nalgebra::Vector3;

/// The mark that opens the comment block; an earlier block is replaced, not stacked.
pub const MARK: &str = "# edbbgen place:";
const END: &str = "# ---";

/// A value the written cell must carry: `[table] key = value` (mm, deg as in the cell file).
#[derive(Clone, Debug, PartialEq)]
pub enum Setting {
    Number(f64),
    Triple([f64; 3]),
}

/// The cell text with `[fixture] position` at `fixture` (m; written in mm with one decimal,
/// which reads back as the same value for positions rounded by [`super::rounded`]), every
/// `(table, key, setting)` in `settings` set, and `header` lines as a comment block on top.
pub fn write(
    input: Option<&str>,
    fixture: &Vector3<f64>,
    settings: &[(&str, &str, Setting)],
    header: &[String],
) -> Result<String, String> {
    let body = strip_block(input.unwrap_or(""));
    let mut doc: toml_edit::DocumentMut = body.parse().map_err(|e| format!("cannot edit: {e}"))?;
    let mm1 = |v: f64| (v * 1e4).round() / 10.0;
    let mut all: Vec<(&str, &str, Setting)> = vec![(
        "fixture",
        "position",
        Setting::Triple([mm1(fixture.x), mm1(fixture.y), mm1(fixture.z)]),
    )];
    all.extend(settings.iter().cloned());
    for (table, key, v) in all {
        let t = doc
            .entry(table)
            .or_insert_with(|| toml_edit::Item::Table(toml_edit::Table::new()))
            .as_table_mut()
            .ok_or_else(|| format!("[{table}] is not a table"))?;
        let mut new = match v {
            Setting::Number(x) => toml_edit::Value::from(x),
            Setting::Triple(a) => {
                let mut arr = toml_edit::Array::new();
                for x in a {
                    arr.push(x);
                }
                toml_edit::Value::Array(arr)
            }
        };
        // Keep the comment that follows the old value on its line.
        if let Some(old) = t.get(key).and_then(|i| i.as_value()) {
            *new.decor_mut() = old.decor().clone();
        }
        t.insert(key, toml_edit::Item::Value(new));
    }
    let mut out = String::from(MARK);
    out.push('\n');
    for l in header {
        out.push_str("# ");
        out.push_str(l);
        out.push('\n');
    }
    out.push_str(END);
    out.push('\n');
    out.push_str(&doc.to_string());
    Ok(out)
}

/// The text without an earlier block (from the mark to its closing line).
fn strip_block(text: &str) -> String {
    let Some(start) = text.find(MARK) else {
        return text.to_string();
    };
    let end_tag = format!("\n{END}\n");
    match text[start..].find(&end_tag) {
        Some(end) => format!("{}{}", &text[..start], &text[start + end + end_tag.len()..]),
        None => text.to_string(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::units::MM;

    #[test]
    fn the_written_cell_reads_back_with_the_new_fixture_and_keeps_the_rest() {
        let input = "# my cell\n[fixture]\nposition = [258.0, 1468.0, 708.0]   # measured 2024\ncone = 55.0\n\n[[environment]]\nname = \"table\"\ntype = \"box\"\nsize = [800.0, 600.0, 700.0]\norigin = [1200.0, -900.0, 350.0]\n";
        let f = super::super::rounded([1311.1, -442.2, 905.0]);
        let text = write(
            Some(input),
            &f,
            &[
                ("fixture", "stand_radius", Setting::Number(40.0)),
                ("bar", "min", Setting::Number(310.0)),
            ],
            &["placed by a test".into()],
        )
        .unwrap();
        assert!(text.starts_with(MARK));
        assert!(text.contains("# my cell") && text.contains("# measured 2024"));
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("c.toml");
        std::fs::write(&p, &text).unwrap();
        let spec = crate::cell::load(&p).unwrap();
        assert_eq!(spec.fixture, Some(f), "the position reads back exactly");
        assert!((spec.fixture_cone - 55f64.to_radians()).abs() < 1e-12);
        assert!((spec.stand_radius - 40.0 * MM).abs() < 1e-15);
        assert!((spec.bar_min - 310.0 * MM).abs() < 1e-15);
        assert_eq!(spec.environment.len(), 1);
        // Written again: one block, not two.
        let again = write(Some(&text), &f, &[], &["second".into()]).unwrap();
        assert_eq!(again.matches(MARK).count(), 1);
        assert!(again.contains("# second") && !again.contains("placed by a test"));
        // No input: a cell with only the fixture.
        let bare = write(None, &f, &[], &[]).unwrap();
        std::fs::write(&p, &bare).unwrap();
        assert_eq!(crate::cell::load(&p).unwrap().fixture, Some(f));
    }
}
