//! Reports for people: in = a stage's results (the compiler's, a diagnosis, a calibration, an
//! LDBB analysis); out = one self-contained HTML page (inline SVG figures and CSS, no script, no
//! network) that opens in any browser and can be handed on.
//!
//! A page is plain data ([`Page`]: sections of figures, tables and notes) rendered by one
//! template (`templates/report.html.j2`). The numbers on a page come from the same structures
//! as the JSON reports, so the page and the JSON cannot disagree. Every figure carries the
//! number of data series it draws (`data-series`), which the browser test checks against what
//! was actually drawn.

pub mod calibrate;
pub mod compensate;
pub mod compile;
pub mod diagnose;
pub mod ldbb;
pub mod place;

use crate::plot::{legend_entries, Figure, Legend, Mark, PlotError};
use serde::Serialize;

/// Schema tag of the page (in a `<meta>`), versioned like the JSON reports.
pub const SCHEMA: &str = "edbbgen.html/1";

#[derive(Clone, Debug, Serialize)]
pub struct Page {
    /// "edbbgen — measurement program", ...
    pub title: String,
    /// Report kind: `compile`, `diagnose`, `calibrate`, `ldbb`.
    pub kind: String,
    pub tool_version: String,
    /// The input hash, as in the program header (empty when the kind has none).
    pub inputs_sha256: String,
    /// Key facts shown at the top: (label, value).
    pub facts: Vec<(String, String)>,
    pub warnings: Vec<String>,
    pub sections: Vec<Section>,
}

#[derive(Clone, Debug, Serialize)]
pub struct Section {
    pub heading: String,
    pub blocks: Vec<Block>,
}

#[derive(Clone, Debug, Serialize)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum Block {
    /// A figure: inline SVG, a caption, the number of series drawn, and a legend of series
    /// names with their palette colours (the SVG has its own legend only where it fits).
    Figure {
        id: String,
        caption: String,
        svg: String,
        series: usize,
        /// (label, colour `#rrggbb`, "line" | "dots" | "segments") for the page's legend.
        legend: Vec<(String, String, String)>,
    },
    Table {
        head: Vec<String>,
        rows: Vec<Vec<String>>,
    },
    Text {
        text: String,
    },
}

impl Block {
    /// Draws `fig` and wraps it with its caption; `series` counts the drawn data series over
    /// all panels.
    pub fn figure(id: &str, caption: &str, fig: &Figure) -> Result<Block, PlotError> {
        Ok(Block::Figure {
            id: id.to_string(),
            caption: caption.to_string(),
            svg: crate::plot::svg(fig)?,
            series: drawn_series(fig),
            legend: if fig.panels.iter().any(|p| p.legend == Legend::Outside) {
                legend_entries(fig)
                    .into_iter()
                    .map(|(l, c, m)| {
                        let m = match m {
                            Mark::Line => "line",
                            Mark::Dots => "dots",
                            Mark::Segments => "segments",
                        };
                        (l, c, m.to_string())
                    })
                    .collect()
            } else {
                Vec::new()
            },
        })
    }

    pub fn table(head: &[&str], rows: Vec<Vec<String>>) -> Block {
        Block::Table {
            head: head.iter().map(|s| s.to_string()).collect(),
            rows,
        }
    }

    pub fn text(text: impl Into<String>) -> Block {
        Block::Text { text: text.into() }
    }
}

/// The number of data series a figure draws, as a browser can count them: distinct (element
/// kind, colour) pairs over the series with data, where a line or segments become SVG
/// polylines and dots become circles. Report figures give every series its own pair (a series
/// repeated in several panels, like the pool in three views, keeps its pair and counts once).
pub fn drawn_series(fig: &Figure) -> usize {
    let mut keys: Vec<(bool, usize)> = fig
        .panels
        .iter()
        .flat_map(|p| &p.series)
        .filter(|s| s.points.iter().any(|q| q.0.is_finite() && q.1.is_finite()))
        .map(|s| (s.mark == Mark::Dots, s.colour % crate::plot::PALETTE_LEN))
        .collect();
    keys.sort_unstable();
    keys.dedup();
    keys.len()
}

#[derive(Debug, thiserror::Error)]
pub enum ReportError {
    #[error(transparent)]
    Plot(#[from] PlotError),
    #[error("report template: {0}")]
    Template(String),
}

const TEMPLATE: &str = include_str!("../../templates/report.html.j2");

/// Renders a page to HTML text (deterministic bytes).
pub fn render(page: &Page) -> Result<String, ReportError> {
    let mut env = minijinja::Environment::new();
    // The `.html` name turns on HTML auto-escaping; SVG is inserted with `|safe`.
    env.add_template("report.html", TEMPLATE)
        .map_err(|e| ReportError::Template(e.to_string()))?;
    let t = env
        .get_template("report.html")
        .map_err(|e| ReportError::Template(e.to_string()))?;
    t.render(minijinja::context! { page => page, schema => SCHEMA })
        .map_err(|e| ReportError::Template(e.to_string()))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::plot::{Panel, Series};

    #[test]
    fn renders_escaped_text_and_counts_series() {
        let fig = Figure {
            title: String::new(),
            panels: vec![Panel {
                series: vec![
                    Series::line("a", 0, vec![(0.0, 0.0), (1.0, 1.0)]),
                    Series::line("empty", 1, vec![]),
                ],
                ..Panel::default()
            }],
            columns: 1,
            panel_px: (300, 200),
        };
        let page = Page {
            title: "t <1>".into(),
            kind: "compile".into(),
            tool_version: "0".into(),
            inputs_sha256: "abc".into(),
            facts: vec![("a & b".into(), "1".into())],
            warnings: vec!["<w>".into()],
            sections: vec![Section {
                heading: "S".into(),
                blocks: vec![
                    Block::figure("f1", "cap", &fig).unwrap(),
                    Block::table(&["x"], vec![vec!["<y>".into()]]),
                ],
            }],
        };
        let html = render(&page).unwrap();
        assert!(html.starts_with("<!DOCTYPE html>"));
        assert!(html.contains("t &lt;1&gt;") && html.contains("a &amp; b"));
        assert!(html.contains("&lt;w&gt;") && html.contains("&lt;y&gt;"));
        assert!(
            html.contains("data-series=\"1\""),
            "the empty series is not counted"
        );
        assert!(html.contains("<svg"));
        assert!(!html.contains("<script"));
        assert_eq!(html, render(&page).unwrap());
    }
}
