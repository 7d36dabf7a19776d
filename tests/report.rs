//! HTML reports in a real browser: Debian's `chromium`, headless, loads each page and a checking
//! script counts, per figure, the data series that were actually drawn (SVG polylines and
//! circles with geometry, by colour) against the figure's `data-series`; any load error fails.
//! A screenshot of each page is kept under `target/report-shots/`.
//!
//! The page itself has no script: the checker is injected into a copy used only here.
//! A missing chromium fails the tests (CI installs it): see [`INSTALL`].

use crate::common::*;
use std::path::{Path, PathBuf};
use std::process::Command;

const INSTALL: &str = "apt-get update && apt-get install -y --no-install-recommends chromium";

/// Flags for a headless run on a machine without network or display (no background
/// connections, no GPU, a fresh profile).
const FLAGS: &[&str] = &[
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--disable-extensions",
    "--hide-scrollbars",
    "--allow-file-access-from-files",
    "--virtual-time-budget=10000",
];

fn chromium() -> PathBuf {
    if let Some(p) = std::env::var_os("CHROMIUM") {
        return PathBuf::from(p);
    }
    let path = std::env::var_os("PATH")
        .map(|p| std::env::split_paths(&p).collect::<Vec<_>>())
        .unwrap_or_default();
    for dir in path.iter().chain([&PathBuf::from("/usr/bin")]) {
        for name in ["chromium", "chromium-browser", "google-chrome"] {
            let p = dir.join(name);
            if p.is_file() {
                return p;
            }
        }
    }
    panic!("chromium is not installed; the report tests need a real browser: run `{INSTALL}`")
}

/// Counts, after load, the drawn series of every figure: distinct (kind, colour) over
/// polylines with ≥ 2 points and a non-empty box, and circles with a radius. Black polylines
/// are the axes and ticks, never data. Errors of any kind (script, resource) are collected.
const CHECKER: &str = r#"<script>
window.__errors = [];
window.addEventListener('error', function (e) {
  window.__errors.push(String(e.message || (e.target && (e.target.src || e.target.href)) || 'error'));
}, true);
window.addEventListener('load', function () {
  var figs = Array.prototype.slice.call(document.querySelectorAll('figure[data-series]'));
  var out = figs.map(function (f) {
    var keys = {};
    var svg = f.querySelector('svg');
    if (svg) {
      svg.querySelectorAll('polyline, circle').forEach(function (el) {
        var bb = el.getBBox();
        if (el.tagName === 'circle') {
          if (parseFloat(el.getAttribute('r')) > 0) keys['circle ' + (el.getAttribute('fill') || '').toUpperCase()] = 1;
        } else {
          var c = (el.getAttribute('stroke') || '').toUpperCase();
          if (c === '#000000' || el.points.numberOfItems < 2 || (bb.width === 0 && bb.height === 0)) return;
          keys['polyline ' + c] = 1;
        }
      });
    }
    var box = svg ? svg.getBoundingClientRect() : { width: 0, height: 0 };
    return { id: f.id, expected: +f.getAttribute('data-series'), drawn: Object.keys(keys).length,
             width: box.width, height: box.height };
  });
  var pre = document.createElement('pre');
  pre.id = 'edbbgen-check';
  pre.textContent = JSON.stringify({ errors: window.__errors, figures: out });
  document.body.appendChild(pre);
});
</script>"#;

#[derive(Debug, serde::Deserialize)]
struct Checked {
    errors: Vec<String>,
    figures: Vec<FigureCheck>,
}

#[derive(Debug, serde::Deserialize)]
struct FigureCheck {
    id: String,
    expected: usize,
    drawn: usize,
    width: f64,
    height: f64,
}

fn unescape(s: &str) -> String {
    s.replace("&quot;", "\"")
        .replace("&lt;", "<")
        .replace("&gt;", ">")
        .replace("&amp;", "&")
}

/// Loads `page` in chromium; returns what the checker saw. Keeps a screenshot as
/// `target/report-shots/<name>.png`.
fn load_in_browser(page: &Path, name: &str) -> Checked {
    let html = std::fs::read_to_string(page).expect("report");
    let dir = tempdir();
    let checked = dir.path().join("check.html");
    std::fs::write(
        &checked,
        html.replacen("<head>", &format!("<head>\n{CHECKER}"), 1),
    )
    .expect("write check copy");
    let profile = dir.path().join("profile");
    let out = Command::new(chromium())
        .args(FLAGS)
        .arg(format!("--user-data-dir={}", profile.display()))
        .arg("--dump-dom")
        .arg(format!("file://{}", checked.display()))
        .output()
        .expect("run chromium");
    assert!(
        out.status.success(),
        "chromium failed: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    let dom = String::from_utf8_lossy(&out.stdout);
    let start = dom
        .find("<pre id=\"edbbgen-check\">")
        .unwrap_or_else(|| panic!("{name}: the checker did not run (page did not load?)"));
    let body = &dom[start + "<pre id=\"edbbgen-check\">".len()..];
    let json = unescape(&body[..body.find("</pre>").expect("end of check")]);

    let shots = root().join("target/report-shots");
    std::fs::create_dir_all(&shots).expect("target/report-shots");
    let shot = shots.join(format!("{name}.png"));
    let out = Command::new(chromium())
        .args(FLAGS)
        .arg(format!("--user-data-dir={}", profile.display()))
        .arg("--window-size=1050,1400")
        .arg(format!("--screenshot={}", shot.display()))
        .arg(format!("file://{}", page.display()))
        .output()
        .expect("run chromium");
    assert!(
        out.status.success() && shot.is_file(),
        "{name}: no screenshot"
    );
    serde_json::from_str(&json).unwrap_or_else(|e| panic!("{name}: checker output {json}: {e}"))
}

/// Every figure drew all its series, the page loaded without an error, and it reaches nothing
/// outside itself.
pub fn assert_page_draws(page: &Path, name: &str, figures: &[&str]) {
    let html = std::fs::read_to_string(page).expect("report");
    let outside = html
        .match_indices("http")
        .filter(|(i, _)| !html[*i..].starts_with("http://www.w3.org/2000/svg"))
        .count();
    assert_eq!(outside, 0, "{name}: the page refers to the network");
    assert!(
        !html.contains("<script"),
        "{name}: the page needs no script"
    );
    let c = load_in_browser(page, name);
    assert!(
        c.errors.is_empty(),
        "{name}: errors while loading: {:?}",
        c.errors
    );
    let ids: Vec<&str> = c.figures.iter().map(|f| f.id.as_str()).collect();
    assert_eq!(ids, figures, "{name}: figures");
    for f in &c.figures {
        assert!(f.expected > 0, "{name}/{}: a figure without data", f.id);
        assert_eq!(f.drawn, f.expected, "{name}/{}: series drawn", f.id);
        assert!(
            f.width > 300.0 && f.height > 150.0,
            "{name}/{}: laid out at {}x{}",
            f.id,
            f.width,
            f.height
        );
    }
}

#[test]
#[ignore = "slow tier: `make test` runs it"]
fn compile_report_draws_in_a_browser() {
    let dir = tempdir();
    let page = dir.path().join("nj130.html");
    let r = edbbgen([
        nj130_dh().as_os_str(),
        "--cell".as_ref(),
        root().join("robots/comau_nj130/cell.toml").as_os_str(),
        "-o".as_ref(),
        dir.path().join("nj130.nc").as_os_str(),
        "--html".as_ref(),
        page.as_os_str(),
        "-q".as_ref(),
    ]);
    assert_eq!(r.code, 0, "{}", r.stderr);
    let html = std::fs::read_to_string(&page).unwrap();
    // The same numbers as the program header and the JSON report.
    let text = std::fs::read_to_string(dir.path().join("nj130.nc")).unwrap();
    let sha = text
        .lines()
        .find_map(|l| l.strip_prefix("(inputs sha256: "))
        .and_then(|l| l.split(')').next())
        .expect("program header names its input hash");
    assert!(
        html.contains(sha),
        "the page states the program's input hash"
    );
    assert!(html.contains(&format!("edbbgen {}", env!("CARGO_PKG_VERSION"))));
    assert_page_draws(
        &page,
        "compile",
        &["fig-poses", "fig-cond", "fig-joints", "fig-path"],
    );
}

#[test]
#[ignore = "slow tier: `make test` runs it"]
fn a_figure_missing_its_series_fails_the_check() {
    // The checker must be able to fail: a page whose figure claims one series more than drawn.
    let dir = tempdir();
    let page = dir.path().join("nj130.html");
    let r = edbbgen([
        nj130_dh().as_os_str(),
        "--fixture".as_ref(),
        "258,1468,708".as_ref(),
        "-o".as_ref(),
        dir.path().join("nj130.nc").as_os_str(),
        "--html".as_ref(),
        page.as_os_str(),
        "-q".as_ref(),
    ]);
    assert_eq!(r.code, 0, "{}", r.stderr);
    let html = std::fs::read_to_string(&page).unwrap();
    let at = html.find("data-series=\"").unwrap() + "data-series=\"".len();
    let end = at + html[at..].find('"').unwrap();
    let n: usize = html[at..end].parse().unwrap();
    let broken = dir.path().join("broken.html");
    std::fs::write(&broken, format!("{}{}{}", &html[..at], n + 1, &html[end..])).unwrap();
    let c = load_in_browser(&broken, "broken");
    assert_eq!(c.figures[0].expected, n + 1);
    assert_eq!(c.figures[0].drawn, n);
}
