//! SVG plot of the residual over time, one panel per diagnosis stage (like the paper's
//! Fig. 12): in = a [`super::Diagnosis`]; out = SVG text. Hand-written SVG (a few polylines)
//! instead of a plotting crate: deterministic bytes and no extra dependency.

use super::Diagnosis;
use crate::units::fmt_fixed;

const W: f64 = 960.0;
const PANEL_H: f64 = 150.0;
const LEFT: f64 = 70.0;
const RIGHT: f64 = 20.0;
const TOP: f64 = 28.0;
const GAP: f64 = 30.0;

/// Renders every stage's residual (µm) against time (s).
pub fn svg(d: &Diagnosis) -> String {
    let n = d.stages.len();
    let h = TOP + n as f64 * (PANEL_H + GAP) + 20.0;
    let mut s = format!(
        "<svg xmlns=\"http://www.w3.org/2000/svg\" width=\"{W}\" height=\"{h}\" viewBox=\"0 0 {W} {h}\" font-family=\"sans-serif\" font-size=\"12\">\n<rect width=\"100%\" height=\"100%\" fill=\"white\"/>\n"
    );
    s += "<text x=\"10\" y=\"18\" font-size=\"14\">EDBB residual (measured - model) over time, after each diagnosis step</text>\n";
    let t0 = d.t.first().copied().unwrap_or(0.0);
    let t1 = d.t.last().copied().unwrap_or(1.0).max(t0 + 1e-9);
    let pw = W - LEFT - RIGHT;
    for (p, (label, r)) in d.stages.iter().enumerate() {
        let y0 = TOP + p as f64 * (PANEL_H + GAP) + 14.0;
        let um: Vec<f64> = r.iter().map(|v| v * 1e6).collect();
        let amax = um.iter().fold(0.0f64, |m, v| m.max(v.abs())).max(1e-3);
        let rms = (um.iter().map(|v| v * v).sum::<f64>() / um.len().max(1) as f64).sqrt();
        s += &format!(
            "<text x=\"{LEFT}\" y=\"{}\">{} — RMS {} µm</text>\n",
            fmt_fixed(y0 - 4.0, 1),
            escape(label),
            fmt_fixed(rms, 3)
        );
        s += &format!(
            "<rect x=\"{LEFT}\" y=\"{}\" width=\"{}\" height=\"{PANEL_H}\" fill=\"none\" stroke=\"#888\"/>\n",
            fmt_fixed(y0, 1),
            fmt_fixed(pw, 1)
        );
        let ymid = y0 + PANEL_H / 2.0;
        s += &format!(
            "<line x1=\"{LEFT}\" y1=\"{m}\" x2=\"{}\" y2=\"{m}\" stroke=\"#ccc\"/>\n",
            fmt_fixed(LEFT + pw, 1),
            m = fmt_fixed(ymid, 1)
        );
        s += &format!(
            "<text x=\"5\" y=\"{}\">{} µm</text>\n<text x=\"5\" y=\"{}\">-{} µm</text>\n",
            fmt_fixed(y0 + 10.0, 1),
            fmt_fixed(amax, 2),
            fmt_fixed(y0 + PANEL_H, 1),
            fmt_fixed(amax, 2)
        );
        // Min/max per pixel column keeps spikes visible.
        let cols = pw as usize;
        let mut lo = vec![f64::MAX; cols];
        let mut hi = vec![f64::MIN; cols];
        for (k, v) in um.iter().enumerate() {
            let c = (((d.t[k] - t0) / (t1 - t0)) * (cols - 1) as f64) as usize;
            lo[c] = lo[c].min(*v);
            hi[c] = hi[c].max(*v);
        }
        let y = |v: f64| ymid - v / amax * (PANEL_H / 2.0 - 4.0);
        let mut pts = String::new();
        for c in 0..cols {
            if lo[c] > hi[c] {
                continue;
            }
            let x = fmt_fixed(LEFT + c as f64, 1);
            pts += &format!(
                "{x},{} {x},{} ",
                fmt_fixed(y(lo[c]), 1),
                fmt_fixed(y(hi[c]), 1)
            );
        }
        s += &format!(
            "<polyline fill=\"none\" stroke=\"#1f5fbf\" stroke-width=\"1\" points=\"{}\"/>\n",
            pts.trim_end()
        );
    }
    let yb = h - 6.0;
    s += &format!(
        "<text x=\"{LEFT}\" y=\"{yb}\">t = {} s</text><text x=\"{}\" y=\"{yb}\" text-anchor=\"end\">t = {} s</text>\n",
        fmt_fixed(t0, 1),
        fmt_fixed(W - RIGHT, 1),
        fmt_fixed(t1, 1)
    );
    s += "</svg>\n";
    s
}

fn escape(s: &str) -> String {
    s.replace('&', "&amp;")
        .replace('<', "&lt;")
        .replace('>', "&gt;")
}
