//! Figures for reports: in = plain series data ([`Figure`] of [`Panel`]s); out = SVG text.
//!
//! The one place that talks to the `plotters` crate, so every report (diagnosis, calibration,
//! LDBB, the compiler's HTML page) draws with the same axes, palette and number format. The
//! output is deterministic bytes: plotters' SVG backend writes integer pixel coordinates and no
//! font is measured from the system (text is laid out by plotters' built-in estimate), so the
//! same data give the same SVG on every machine.
//!
//! Long series (a 30,000-row measurement) are reduced to a min/max envelope per pixel column
//! ([`envelope`]) before drawing: the picture is the same, spikes stay visible, and the SVG
//! stays small enough to inline in an HTML page.

use plotters::coord::Shift;
use plotters::prelude::*;

/// How a series is drawn.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Mark {
    /// A polyline through the points in order; a non-finite point breaks the line.
    Line,
    /// A small filled circle per point.
    Dots,
    /// A straight segment per consecutive pair of points: (p0, p1), (p2, p3), ...
    Segments,
}

/// One data series of a panel.
#[derive(Clone, Debug, PartialEq)]
pub struct Series {
    /// Legend text; empty = no legend entry.
    pub label: String,
    pub points: Vec<(f64, f64)>,
    pub mark: Mark,
    /// Index into the palette; series with the same index share a colour.
    pub colour: usize,
}

impl Series {
    pub fn line(label: impl Into<String>, colour: usize, points: Vec<(f64, f64)>) -> Self {
        Series {
            label: label.into(),
            points,
            mark: Mark::Line,
            colour,
        }
    }

    pub fn dots(label: impl Into<String>, colour: usize, points: Vec<(f64, f64)>) -> Self {
        Series {
            label: label.into(),
            points,
            mark: Mark::Dots,
            colour,
        }
    }
}

/// One chart: axes, series, optional fixed ranges.
#[derive(Clone, Debug, PartialEq, Default)]
pub struct Panel {
    pub title: String,
    pub x_label: String,
    pub y_label: String,
    pub series: Vec<Series>,
    /// Fixed axis ranges; `None` = fit the data (with 4 % padding).
    pub x_range: Option<(f64, f64)>,
    pub y_range: Option<(f64, f64)>,
    /// Same scale on both axes (for drawings of space, e.g. a pose cloud in a plane).
    pub equal_aspect: bool,
    /// Logarithmic y axis (base 10): the data stay as given; non-positive values are not drawn.
    pub y_log: bool,
    /// Where the legend of the labelled series goes.
    pub legend: Legend,
}

/// Legend placement. `Outside` draws none in the SVG: the page around the figure shows the
/// series names with their colours instead (see [`legend_entries`]), for small panels where a
/// legend would hide the data.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default)]
pub enum Legend {
    #[default]
    UpperRight,
    LowerRight,
    Outside,
}

/// The distinct (label, colour as `#rrggbb`, mark) of a figure's labelled series, in first-seen
/// order: the legend a page draws for `Legend::Outside` panels.
pub fn legend_entries(fig: &Figure) -> Vec<(String, String, Mark)> {
    let mut out: Vec<(String, String, Mark)> = Vec::new();
    for s in fig.panels.iter().flat_map(|p| &p.series) {
        if !s.label.is_empty() && !out.iter().any(|e| e.0 == s.label) {
            out.push((s.label.clone(), colour_hex(s.colour), s.mark));
        }
    }
    out
}

/// A figure: a title and panels in a grid of `columns` columns, each `panel_px` pixels.
#[derive(Clone, Debug, PartialEq)]
pub struct Figure {
    pub title: String,
    pub panels: Vec<Panel>,
    pub columns: usize,
    pub panel_px: (u32, u32),
}

#[derive(Debug, thiserror::Error)]
pub enum PlotError {
    #[error("plot '{title}': {message}")]
    Draw { title: String, message: String },
}

/// Number of distinct palette colours; colour indices are taken modulo this.
pub const PALETTE_LEN: usize = 9;

/// Colour-blind-safe palette (Okabe-Ito), then greys. Index modulo its length.
const PALETTE: [RGBColor; PALETTE_LEN] = [
    RGBColor(0, 114, 178),   // blue
    RGBColor(213, 94, 0),    // vermillion
    RGBColor(0, 158, 115),   // bluish green
    RGBColor(204, 121, 167), // reddish purple
    RGBColor(230, 159, 0),   // orange
    RGBColor(86, 180, 233),  // sky blue
    RGBColor(240, 228, 66),  // yellow
    RGBColor(0, 0, 0),       // black
    RGBColor(136, 136, 136), // grey
];

/// The palette colour of index `i` as `#rrggbb` (for HTML legends next to a figure).
pub fn colour_hex(i: usize) -> String {
    let c = PALETTE[i % PALETTE.len()];
    format!("#{:02x}{:02x}{:02x}", c.0, c.1, c.2)
}

/// Renders a figure to SVG text.
pub fn svg(fig: &Figure) -> Result<String, PlotError> {
    let columns = fig.columns.max(1);
    let rows = fig.panels.len().div_ceil(columns).max(1);
    let title_h = if fig.title.is_empty() { 0 } else { 30 };
    let w = fig.panel_px.0 * columns as u32;
    let h = fig.panel_px.1 * rows as u32 + title_h;
    let mut out = String::new();
    {
        let root = SVGBackend::with_string(&mut out, (w, h)).into_drawing_area();
        let err = |title: &str, e: &dyn std::fmt::Display| PlotError::Draw {
            title: title.to_string(),
            message: e.to_string(),
        };
        root.fill(&WHITE).map_err(|e| err(&fig.title, &e))?;
        let body = if fig.title.is_empty() {
            root.clone()
        } else {
            root.titled(&fig.title, ("sans-serif", 18))
                .map_err(|e| err(&fig.title, &e))?
        };
        let areas = body.split_evenly((rows, columns));
        for (panel, area) in fig.panels.iter().zip(areas.iter()) {
            draw_panel(panel, area).map_err(|m| PlotError::Draw {
                title: format!("{} / {}", fig.title, panel.title),
                message: m,
            })?;
        }
        root.present().map_err(|e| err(&fig.title, &e))?;
    }
    Ok(out)
}

/// The data range of the finite values, padded by 4 % (a flat series gets ±1 around its value).
fn fit_range(values: impl Iterator<Item = f64>) -> (f64, f64) {
    let (lo, hi) = values
        .filter(|v| v.is_finite())
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), v| {
            (a.min(v), b.max(v))
        });
    if !lo.is_finite() {
        return (0.0, 1.0);
    }
    let span = hi - lo;
    if span <= 1e-12 * lo.abs().max(1.0) {
        return (lo - 1.0, hi + 1.0);
    }
    (lo - 0.04 * span, hi + 0.04 * span)
}

/// A log axis only pays when the data span more than this ratio; below it a linear axis reads better.
const LOG_MIN_RATIO: f64 = 30.0;

fn draw_panel(p: &Panel, area: &DrawingArea<SVGBackend, Shift>) -> Result<(), String> {
    let positive = p
        .series
        .iter()
        .flat_map(|s| s.points.iter().map(|q| q.1))
        .filter(|y| y.is_finite() && *y > 0.0);
    let (lo, hi) = positive.fold((f64::INFINITY, 0.0f64), |(a, b), y| (a.min(y), b.max(y)));
    if p.y_log && hi > LOG_MIN_RATIO * lo {
        // Drawn as log10(y) on a linear axis, labelled with y itself.
        let log = |q: &(f64, f64)| (q.0, if q.1 > 0.0 { q.1.log10() } else { f64::NAN });
        let mut lp = p.clone();
        lp.y_log = false;
        lp.y_range = p.y_range.map(|(a, b)| (a.log10(), b.log10()));
        for s in &mut lp.series {
            s.points = s.points.iter().map(log).collect();
        }
        return draw_linear(&lp, area, true);
    }
    draw_linear(p, area, false)
}

fn draw_linear(
    p: &Panel,
    area: &DrawingArea<SVGBackend, Shift>,
    y_is_log10: bool,
) -> Result<(), String> {
    let all = || p.series.iter().flat_map(|s| s.points.iter());
    let mut xr = p.x_range.unwrap_or_else(|| fit_range(all().map(|q| q.0)));
    let mut yr = p.y_range.unwrap_or_else(|| fit_range(all().map(|q| q.1)));
    if p.equal_aspect {
        // Widen the shorter range so one data unit spans the same pixels on both axes.
        let (pw, ph) = area.dim_in_pixel();
        let (pw, ph) = ((pw as f64 - 70.0).max(1.0), (ph as f64 - 70.0).max(1.0));
        let sx = (xr.1 - xr.0) / pw;
        let sy = (yr.1 - yr.0) / ph;
        if sx > sy {
            let c = 0.5 * (yr.0 + yr.1);
            yr = (c - 0.5 * sx * ph, c + 0.5 * sx * ph);
        } else {
            let c = 0.5 * (xr.0 + xr.1);
            xr = (c - 0.5 * sy * pw, c + 0.5 * sy * pw);
        }
    }
    let mut chart = ChartBuilder::on(area)
        .caption(&p.title, ("sans-serif", 14))
        .margin(8)
        .x_label_area_size(34)
        .y_label_area_size(58)
        .build_cartesian_2d(xr.0..xr.1, yr.0..yr.1)
        .map_err(|e| e.to_string())?;
    let (w_px, h_px) = area.dim_in_pixel();
    chart
        .configure_mesh()
        .x_labels((w_px as usize / 90).clamp(3, 12))
        .y_labels((h_px as usize / 45).clamp(3, 12))
        .x_desc(p.x_label.as_str())
        .y_desc(p.y_label.as_str())
        .light_line_style(WHITE.mix(0.0))
        .bold_line_style(BLACK.mix(0.08))
        .label_style(("sans-serif", 11))
        .x_label_formatter(&|v| tick(*v))
        .y_label_formatter(&|v| {
            if y_is_log10 {
                tick(10f64.powf(*v))
            } else {
                tick(*v)
            }
        })
        .draw()
        .map_err(|e| e.to_string())?;
    let mut legend = false;
    for s in &p.series {
        let colour = PALETTE[s.colour % PALETTE.len()];
        let style = ShapeStyle::from(&colour).stroke_width(1);
        let anno = match s.mark {
            Mark::Line => chart
                .draw_series(
                    // More points than pixel columns draw the same picture as their envelope.
                    runs(&s.points)
                        .into_iter()
                        .map(|run| PathElement::new(envelope(&run, w_px as usize), style)),
                )
                .map_err(|e| e.to_string())?,
            Mark::Segments => chart
                .draw_series(
                    s.points
                        .chunks_exact(2)
                        .filter(|c| finite(c[0]) && finite(c[1]))
                        .map(|c| PathElement::new(vec![c[0], c[1]], style)),
                )
                .map_err(|e| e.to_string())?,
            Mark::Dots => chart
                .draw_series(
                    s.points
                        .iter()
                        .filter(|q| finite(**q))
                        .map(|q| Circle::new(*q, 2, colour.filled())),
                )
                .map_err(|e| e.to_string())?,
        };
        if !s.label.is_empty() && p.legend != Legend::Outside {
            legend = true;
            let mark = s.mark;
            anno.label(s.label.as_str()).legend(move |(x, y)| {
                let e: DynElement<SVGBackend, (i32, i32)> = match mark {
                    Mark::Dots => Circle::new((x + 8, y), 3, colour.filled()).into_dyn(),
                    _ => PathElement::new(vec![(x, y), (x + 16, y)], style).into_dyn(),
                };
                e
            });
        }
    }
    if legend {
        chart
            .configure_series_labels()
            .position(if p.legend == Legend::LowerRight {
                SeriesLabelPosition::LowerRight
            } else {
                SeriesLabelPosition::UpperRight
            })
            .background_style(WHITE.mix(0.85))
            .border_style(BLACK.mix(0.3))
            .label_font(("sans-serif", 11))
            .draw()
            .map_err(|e| e.to_string())?;
    }
    Ok(())
}

fn finite(q: (f64, f64)) -> bool {
    q.0.is_finite() && q.1.is_finite()
}

/// Splits a polyline at non-finite points; runs of one point are kept (a dot of a line).
fn runs(points: &[(f64, f64)]) -> Vec<Vec<(f64, f64)>> {
    let mut out = Vec::new();
    let mut cur = Vec::new();
    for &q in points {
        if finite(q) {
            cur.push(q);
        } else if !cur.is_empty() {
            out.push(std::mem::take(&mut cur));
        }
    }
    if !cur.is_empty() {
        out.push(cur);
    }
    out
}

/// Tick labels: up to 4 significant digits, no trailing zeros, no "-0".
fn tick(v: f64) -> String {
    if v == 0.0 || !v.is_finite() {
        return "0".to_string();
    }
    let mag = v.abs().log10().floor() as i32;
    if !(-3..6).contains(&mag) {
        return format!("{v:.2e}");
    }
    let decimals = (3 - mag).clamp(0, 6) as usize;
    let s = format!("{v:.decimals$}");
    let s = if s.contains('.') {
        s.trim_end_matches('0').trim_end_matches('.').to_string()
    } else {
        s
    };
    if s == "-0" {
        "0".to_string()
    } else {
        s
    }
}

/// The x axis of a residual or a length over a run: its times (s), or for untimed static
/// readings, whose `t` is the order taken (0, 1, ...), the reading number from 1.
pub fn run_axis(t: &[f64], timed: bool) -> (Vec<f64>, &'static str) {
    if timed {
        (t.to_vec(), "t [s]")
    } else {
        (t.iter().map(|k| k + 1.0).collect(), "reading")
    }
}

/// Inserts a break (a NaN point) wherever consecutive x values are more than `factor` times the
/// median x step apart, so that a recording with pauses (sections of a program, the bar
/// remounted) is not drawn as a straight line across the pause.
pub fn break_gaps(points: &[(f64, f64)], factor: f64) -> Vec<(f64, f64)> {
    if points.len() < 3 {
        return points.to_vec();
    }
    let mut steps: Vec<f64> = points.windows(2).map(|w| w[1].0 - w[0].0).collect();
    steps.sort_by(f64::total_cmp);
    let limit = factor * steps[steps.len() / 2];
    let mut out = Vec::with_capacity(points.len() + 8);
    out.push(points[0]);
    for w in points.windows(2) {
        if w[1].0 - w[0].0 > limit {
            out.push((f64::NAN, f64::NAN));
        }
        out.push(w[1]);
    }
    out
}

/// Min/max envelope of a long series over `columns` equal x bins: two points per non-empty bin
/// (at the bin's min and max y, in x order of occurrence), so a plot of the result looks like a
/// plot of the original at that width. Series no longer than 2·columns are returned unchanged.
pub fn envelope(points: &[(f64, f64)], columns: usize) -> Vec<(f64, f64)> {
    let columns = columns.max(1);
    if points.len() <= 2 * columns {
        return points.to_vec();
    }
    let (x0, x1) = fit_range(points.iter().map(|q| q.0));
    let span = (x1 - x0).max(f64::MIN_POSITIVE);
    // Per bin: (x at min, min, x at max, max).
    let mut bins: Vec<Option<(f64, f64, f64, f64)>> = vec![None; columns];
    for &(x, y) in points {
        if !(x.is_finite() && y.is_finite()) {
            continue;
        }
        let c = (((x - x0) / span) * columns as f64) as usize;
        let b = &mut bins[c.min(columns - 1)];
        *b = Some(match *b {
            None => (x, y, x, y),
            Some((xl, lo, xh, hi)) => {
                let (xl, lo) = if y < lo { (x, y) } else { (xl, lo) };
                let (xh, hi) = if y > hi { (x, y) } else { (xh, hi) };
                (xl, lo, xh, hi)
            }
        });
    }
    let mut out = Vec::with_capacity(2 * columns);
    for (xl, lo, xh, hi) in bins.into_iter().flatten() {
        if xl <= xh {
            out.push((xl, lo));
            out.push((xh, hi));
        } else {
            out.push((xh, hi));
            out.push((xl, lo));
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    fn panel(series: Vec<Series>) -> Panel {
        Panel {
            title: "p".into(),
            x_label: "x".into(),
            y_label: "y".into(),
            series,
            ..Panel::default()
        }
    }

    fn sine(n: usize) -> Vec<(f64, f64)> {
        (0..n)
            .map(|i| {
                let x = i as f64 / n as f64 * 10.0;
                (x, x.sin())
            })
            .collect()
    }

    /// Polylines drawn in a palette colour (the axes and ticks are black/grey, so colour 0 is
    /// unambiguous).
    fn count_stroke(svg: &str, colour: usize) -> usize {
        let hex = colour_hex(colour).to_uppercase();
        svg.lines()
            .filter(|l| l.starts_with("<polyline") && l.contains(&format!("stroke=\"{hex}\"")))
            .count()
    }

    #[test]
    fn draws_every_series_and_is_deterministic() {
        let fig = Figure {
            title: "two panels".into(),
            panels: vec![
                panel(vec![
                    Series::line("a", 0, sine(500)),
                    Series::line("", 1, sine(50)),
                ]),
                panel(vec![Series::dots("pts", 2, sine(20))]),
            ],
            columns: 2,
            panel_px: (400, 300),
        };
        let a = svg(&fig).unwrap();
        let b = svg(&fig).unwrap();
        assert_eq!(a, b);
        assert!(a.starts_with("<svg"));
        // series a: one polyline + one legend sample; series 2: 20 dots + 1 legend dot.
        assert_eq!(count_stroke(&a, 0), 2);
        assert_eq!(count_stroke(&a, 1), 1);
        let dots = a
            .lines()
            .filter(|l| l.starts_with("<circle") && l.contains(&colour_hex(2).to_uppercase()))
            .count();
        assert_eq!(dots, 21);
        assert!(a.contains(">\npts\n<") || a.contains("pts"));
    }

    #[test]
    fn non_finite_points_break_the_line_and_empty_panels_draw() {
        let mut pts = sine(100);
        pts[50].1 = f64::NAN;
        let fig = Figure {
            title: String::new(),
            panels: vec![panel(vec![Series::line("", 0, pts)]), panel(vec![])],
            columns: 1,
            panel_px: (300, 200),
        };
        let s = svg(&fig).unwrap();
        assert_eq!(count_stroke(&s, 0), 2);
    }

    #[test]
    fn envelope_keeps_extremes_and_bounds_size() {
        let mut pts = sine(30_000);
        pts[12_345].1 = 7.0; // a spike
        let e = envelope(&pts, 400);
        assert!(e.len() <= 800);
        let max = e.iter().map(|q| q.1).fold(f64::MIN, f64::max);
        let min = e.iter().map(|q| q.1).fold(f64::MAX, f64::min);
        assert_eq!(max, 7.0);
        let true_min = pts.iter().map(|q| q.1).fold(f64::MAX, f64::min);
        assert_eq!(min, true_min);
        // x stays ordered
        assert!(e.windows(2).all(|w| w[0].0 <= w[1].0));
        // short series unchanged
        assert_eq!(envelope(&pts[..100], 400), pts[..100].to_vec());
    }

    #[test]
    fn gaps_break_the_line() {
        let mut pts: Vec<(f64, f64)> = (0..100).map(|i| (i as f64 * 0.02, 0.0)).collect();
        pts.extend((0..100).map(|i| (5.0 + i as f64 * 0.02, 1.0)));
        let b = break_gaps(&pts, 5.0);
        assert_eq!(b.len(), 201);
        assert!(b[100].0.is_nan());
        assert_eq!(runs(&b).len(), 2);
    }

    #[test]
    fn ticks_read_like_numbers() {
        assert_eq!(tick(0.0), "0");
        assert_eq!(tick(2.5), "2.5");
        assert_eq!(tick(-1200.0), "-1200");
        assert_eq!(tick(0.0125), "0.0125");
        assert_eq!(tick(1.0e7), "1.00e7");
    }
}
