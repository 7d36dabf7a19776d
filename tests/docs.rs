//! The documentation as a user follows it: every shell block of README.md and docs/ runs as
//! written on shipped inputs and prints what the page shows; every relative link and anchor of
//! README.md, CONTRIBUTING.md and docs/ resolves.
//!
//! A page's ```` ```sh ```` blocks run in order in one bash session (variables and the working
//! folder carry over from block to block), from a scratch folder that looks like the
//! repository's top folder (`robots`, `examples`, `docs`, `templates` and `../shared` reach the
//! real ones). Commands named `edbbgen` run the binary under test. A ```` ```text ```` block
//! right after a shell block is its expected output (stdout and stderr as a terminal shows
//! them): compared line by line, trailing spaces ignored; a line `...` stands for any number of
//! lines, and a line ending in `...` for any line that starts with what precedes it. A block
//! marked ```` ```sh no-run ```` (installing, building, the make targets) is not run.
//!
//! After a change of output, `EDBBGEN_UPDATE_DOCS=1 cargo test --locked --test main docs`
//! rewrites every expected block without `...` with what the commands print now; review the
//! diff in git like a snapshot.

use crate::common::*;
use std::collections::BTreeSet;
use std::path::{Path, PathBuf};
use std::process::Command;

/// One fenced code block of a Markdown file.
#[derive(Debug)]
struct Block {
    /// The info string's words (`sh`, `no-run`, `text`, ...).
    info: Vec<String>,
    /// Line index of the opening fence (0-based).
    open: usize,
    /// Line index of the closing fence.
    close: usize,
    body: Vec<String>,
}

/// The fenced blocks of a Markdown text (``` fences, possibly indented as in a list item).
fn blocks(text: &str) -> Vec<Block> {
    let lines: Vec<&str> = text.lines().collect();
    let mut out = Vec::new();
    let mut i = 0;
    while i < lines.len() {
        let t = lines[i].trim_start();
        if let Some(info) = t.strip_prefix("```") {
            let indent = lines[i].len() - t.len();
            let fence_len = 3 + info.chars().take_while(|c| *c == '`').count();
            let info = info.trim_start_matches('`');
            let words = info
                .split(|c: char| c.is_whitespace() || c == ',')
                .filter(|w| !w.is_empty())
                .map(str::to_string)
                .collect();
            let mut body = Vec::new();
            let mut j = i + 1;
            while j < lines.len() {
                let u = lines[j].trim_start();
                if u.starts_with(&"`".repeat(fence_len)) && u.trim_end().chars().all(|c| c == '`') {
                    break;
                }
                let l = lines[j];
                let cut = l.len() - l.trim_start().len();
                body.push(l[cut.min(indent)..].to_string());
                j += 1;
            }
            out.push(Block {
                info: words,
                open: i,
                close: j,
                body,
            });
            i = j + 1;
        } else {
            i += 1;
        }
    }
    out
}

impl Block {
    fn runs(&self) -> bool {
        self.info.first().is_some_and(|w| w == "sh") && !self.info.iter().any(|w| w == "no-run")
    }
    fn is_output(&self) -> bool {
        self.info.first().is_some_and(|w| w == "text")
    }
}

/// Does the actual output match the expected lines (`...` = any lines, `prefix...` = a line
/// starting with prefix)?
fn matches(expected: &[String], actual: &[&str]) -> bool {
    match expected.first() {
        None => actual.is_empty(),
        Some(e) if e.trim() == "..." => {
            (0..=actual.len()).any(|k| matches(&expected[1..], &actual[k..]))
        }
        Some(e) => {
            let Some(a) = actual.first() else {
                return false;
            };
            let e = e.trim_end();
            let ok = match e.strip_suffix("...") {
                Some(prefix) => a.starts_with(prefix),
                None => e == *a,
            };
            ok && matches(&expected[1..], &actual[1..])
        }
    }
}

fn normalise(text: &str) -> Vec<String> {
    let mut lines: Vec<String> = text.lines().map(|l| l.trim_end().to_string()).collect();
    while lines.last().is_some_and(|l| l.is_empty()) {
        lines.pop();
    }
    while lines.first().is_some_and(|l| l.is_empty()) {
        lines.remove(0);
    }
    lines
}

const MARK: &str = "@@edbbgen-docs-block-end@@";

/// A scratch folder laid out like a checkout: `DIR/checkout` (the working folder) holds links to
/// the repository's inputs and `DIR/shared` reaches ../shared; `DIR/bin/edbbgen` is the binary
/// under test.
fn scratch() -> (tempfile::TempDir, PathBuf, PathBuf) {
    let dir = tempdir();
    let work = dir.path().join("checkout");
    let bin = dir.path().join("bin");
    std::fs::create_dir_all(&work).unwrap();
    std::fs::create_dir_all(&bin).unwrap();
    let root = root();
    for name in ["robots", "examples", "docs", "templates"] {
        std::os::unix::fs::symlink(root.join(name), work.join(name)).unwrap();
    }
    std::os::unix::fs::symlink(root.join("../shared"), dir.path().join("shared")).unwrap();
    std::os::unix::fs::symlink(env!("CARGO_BIN_EXE_edbbgen"), bin.join("edbbgen")).unwrap();
    (dir, work, bin)
}

/// What went wrong on one page, one line per problem (the full outputs follow).
struct PageRun {
    failures: Vec<String>,
    /// (line of the expected block's opening fence, new body) for the update mode.
    updates: Vec<(usize, usize, Vec<String>)>,
    work: PathBuf,
    _dir: tempfile::TempDir,
}

/// Runs the page's shell blocks in one bash session and compares each output with the page.
fn run_page(rel: &str) -> PageRun {
    let text = std::fs::read_to_string(root().join(rel)).unwrap();
    let all = blocks(&text);
    let (dir, work, bin) = scratch();
    let mut script = String::from("exec 2>&1\nset -e\n");
    let mut runnable = Vec::new();
    for (k, b) in all.iter().enumerate() {
        if !b.runs() {
            continue;
        }
        for l in &b.body {
            script.push_str(l);
            script.push('\n');
        }
        script.push_str(&format!("printf '\\n%s\\n' '{MARK}'\n"));
        runnable.push(k);
    }
    let mut failures = Vec::new();
    let mut updates = Vec::new();
    if runnable.is_empty() {
        return PageRun {
            failures,
            updates,
            work,
            _dir: dir,
        };
    }
    let path = format!(
        "{}:{}",
        bin.display(),
        std::env::var("PATH").unwrap_or_default()
    );
    let out = Command::new("bash")
        .arg("-c")
        .arg(&script)
        .current_dir(&work)
        .env("PATH", path)
        .env_remove("EDBBGEN_UPDATE_DOCS")
        .output()
        .expect("run bash");
    let stdout = String::from_utf8_lossy(&out.stdout).into_owned();
    let parts: Vec<&str> = stdout.split(MARK).collect();
    for (n, &k) in runnable.iter().enumerate() {
        let b = &all[k];
        let Some(part) = parts.get(n).filter(|_| n + 1 < parts.len()) else {
            failures.push(format!(
                "{rel}:{}: this block failed (exit {:?}); what it printed:\n{}",
                b.open + 1,
                out.status.code(),
                parts.last().unwrap_or(&"")
            ));
            break;
        };
        let actual = normalise(part);
        // The expected output: a ```text block right after (blank lines between allowed).
        let lines: Vec<&str> = text.lines().collect();
        let next = all.get(k + 1).filter(|nb| {
            nb.is_output()
                && lines[b.close + 1..nb.open]
                    .iter()
                    .all(|l| l.trim().is_empty())
        });
        if let Some(nb) = next {
            let refs: Vec<&str> = actual.iter().map(String::as_str).collect();
            let expected = normalise(&nb.body.join("\n"));
            if !matches(&expected, &refs) {
                failures.push(format!(
                    "{rel}:{}: the output differs from the page's (line {}); it prints:\n{}\n",
                    b.open + 1,
                    nb.open + 1,
                    actual.join("\n")
                ));
                if !expected.iter().any(|l| l.trim_end().ends_with("...")) {
                    updates.push((nb.open, nb.close, actual.clone()));
                }
            }
        }
    }
    PageRun {
        failures,
        updates,
        work,
        _dir: dir,
    }
}

/// The update mode: rewrite the expected blocks with what the commands print now.
fn update(rel: &str, updates: &[(usize, usize, Vec<String>)]) {
    let path = root().join(rel);
    let text = std::fs::read_to_string(&path).unwrap();
    let mut lines: Vec<String> = text.lines().map(str::to_string).collect();
    for (open, close, body) in updates.iter().rev() {
        let indent: String = lines[*open]
            .chars()
            .take_while(|c| c.is_whitespace())
            .collect();
        let new: Vec<String> = body
            .iter()
            .map(|l| {
                if l.is_empty() {
                    String::new()
                } else {
                    format!("{indent}{l}")
                }
            })
            .collect();
        lines.splice(open + 1..*close, new);
    }
    let mut out = lines.join("\n");
    out.push('\n');
    std::fs::write(&path, out).unwrap();
}

fn check_pages(pages: &[String]) -> Vec<PageRun> {
    let update_mode = std::env::var_os("EDBBGEN_UPDATE_DOCS").is_some();
    let mut runs = Vec::new();
    let mut failures = Vec::new();
    for rel in pages {
        let run = run_page(rel);
        if update_mode && !run.updates.is_empty() {
            update(rel, &run.updates);
        }
        failures.extend(run.failures.iter().cloned());
        runs.push(run);
    }
    assert!(
        failures.is_empty() || update_mode,
        "{} shell block(s) of the docs do not do what the page says:\n\n{}\n\
         (EDBBGEN_UPDATE_DOCS=1 rewrites the expected outputs that hold no `...`)",
        failures.len(),
        failures.join("\n")
    );
    runs
}

/// README.md, CONTRIBUTING.md and every Markdown file under docs/, as paths from the root.
fn doc_files() -> Vec<String> {
    let root = root();
    let mut out = vec!["README.md".to_string(), "CONTRIBUTING.md".to_string()];
    let mut stack = vec![root.join("docs")];
    let mut found = Vec::new();
    while let Some(dir) = stack.pop() {
        for e in std::fs::read_dir(&dir).unwrap() {
            let p = e.unwrap().path();
            if p.is_dir() {
                stack.push(p);
            } else if p.extension().is_some_and(|x| x == "md") {
                found.push(
                    p.strip_prefix(&root)
                        .unwrap()
                        .to_string_lossy()
                        .into_owned(),
                );
            }
        }
    }
    found.sort();
    out.extend(found);
    out
}

#[test]
fn the_commissioning_tutorial_runs_on_shipped_inputs_and_prints_what_it_shows() {
    let runs = check_pages(&["docs/tutorial.md".to_string()]);
    // What the tutorial promises a new user ends with, read from the files themselves.
    let w = &runs[0].work;
    let nj = w.join("nj130");
    for f in [
        "nj130.nc",
        "nj130.html",
        "measured.csv",
        "nj130.cal.dh.toml",
        "cal.json",
        "targets.comp.csv",
        "pick.comp.nc",
        "check.nc",
        "now.json",
    ] {
        assert!(nj.join(f).is_file(), "the tutorial did not write {f}");
    }
    // The calibrated robot loads like any robot file.
    let r = edbbgen([
        "model",
        nj.join("nj130.cal.dh.toml").to_str().unwrap(),
        "--fixture",
        "258,1468,708",
    ]);
    assert_eq!(r.code, 0, "{}", r.stderr);
    // Every compensated target is compensated.
    let comp = std::fs::read_to_string(nj.join("targets.comp.csv")).unwrap();
    let rows: Vec<&str> = comp.lines().skip(1).collect();
    assert!(!rows.is_empty());
    for row in rows {
        assert!(row.ends_with(",ok"), "not compensated: {row}");
    }
    // The check a month later names the joint whose zero moved.
    let now: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(nj.join("now.json")).unwrap()).unwrap();
    let moved = now["drift"]["moved"].to_string();
    assert!(moved.contains("theta2"), "drift.moved = {moved}");
}

#[test]
fn every_other_shell_block_of_the_docs_runs_and_prints_what_its_page_shows() {
    let pages: Vec<String> = doc_files()
        .into_iter()
        .filter(|p| p != "docs/tutorial.md")
        .collect();
    check_pages(&pages);
}

/// GitHub's and mdBook's anchor of a heading: lowercase, letters, digits, `-` and `_` kept,
/// spaces to `-`, everything else dropped.
fn slug(heading: &str) -> String {
    let mut s = String::new();
    for c in heading.trim().chars() {
        if c == ' ' {
            s.push('-');
        } else if c.is_alphanumeric() || c == '-' || c == '_' {
            s.extend(c.to_lowercase());
        }
    }
    s
}

/// The anchors a Markdown file defines: its headings' slugs (repeats get `-1`, `-2`, ...) and
/// explicit `<a id="...">` / `<a name="...">`.
fn anchors(text: &str) -> BTreeSet<String> {
    let mut out = BTreeSet::new();
    let mut fenced = false;
    for line in text.lines() {
        if line.trim_start().starts_with("```") {
            fenced = !fenced;
            continue;
        }
        if fenced {
            continue;
        }
        if let Some(h) = line.strip_prefix('#') {
            let h = h.trim_start_matches('#');
            if h.starts_with(' ') {
                // Inline markup the renderers drop: backticks, emphasis, link targets.
                let mut plain = String::new();
                let mut skip_target = false;
                let chars: Vec<char> = h.chars().collect();
                for (i, &c) in chars.iter().enumerate() {
                    if skip_target {
                        if c == ')' {
                            skip_target = false;
                        }
                        continue;
                    }
                    if c == ']' && chars.get(i + 1) == Some(&'(') {
                        skip_target = true;
                        continue;
                    }
                    if c != '[' && c != '`' && c != '*' {
                        plain.push(c);
                    }
                }
                let base = slug(&plain);
                let mut a = base.clone();
                let mut n = 1;
                while out.contains(&a) {
                    a = format!("{base}-{n}");
                    n += 1;
                }
                out.insert(a);
            }
        }
        for key in ["<a id=\"", "<a name=\""] {
            for part in line.split(key).skip(1) {
                if let Some(id) = part.split('"').next() {
                    out.insert(id.to_string());
                }
            }
        }
    }
    out
}

/// The targets of a Markdown file's inline links and images outside code: `](target)`.
fn links(text: &str) -> Vec<(usize, String)> {
    let mut out = Vec::new();
    let mut fenced = false;
    for (n, line) in text.lines().enumerate() {
        if line.trim_start().starts_with("```") {
            fenced = !fenced;
            continue;
        }
        if fenced {
            continue;
        }
        // Drop inline code spans.
        let mut plain = String::new();
        let mut in_code = false;
        for c in line.chars() {
            if c == '`' {
                in_code = !in_code;
            } else if !in_code {
                plain.push(c);
            }
        }
        for part in plain.split("](").skip(1) {
            if let Some(end) = part.find(')') {
                let target = part[..end].split_whitespace().next().unwrap_or("");
                out.push((n + 1, target.to_string()));
            }
        }
    }
    out
}

#[test]
fn every_relative_link_and_anchor_in_the_docs_resolves() {
    let root = root();
    let mut problems = Vec::new();
    let files = doc_files();
    assert!(files.len() > 10, "the docs: {files:?}");
    for rel in &files {
        let path = root.join(rel);
        let text = std::fs::read_to_string(&path).unwrap();
        for (line, target) in links(&text) {
            if target.contains("://") || target.starts_with("mailto:") || target.is_empty() {
                continue;
            }
            let (file, anchor) = match target.split_once('#') {
                Some((f, a)) => (f, Some(a)),
                None => (target.as_str(), None),
            };
            let dest: PathBuf = if file.is_empty() {
                path.clone()
            } else {
                path.parent().unwrap().join(file)
            };
            let Ok(dest) = dest.canonicalize() else {
                problems.push(format!("{rel}:{line}: {target}: no such file"));
                continue;
            };
            // A page of the book links only inside the book: mdBook renders nothing else.
            if rel.starts_with("docs/")
                && !dest.starts_with(root.join("docs").canonicalize().unwrap())
            {
                problems.push(format!(
                    "{rel}:{line}: {target}: outside docs/ (the book cannot link there; name the file in code instead)"
                ));
                continue;
            }
            if let Some(a) = anchor {
                if dest.extension().is_none_or(|x| x != "md") {
                    problems.push(format!(
                        "{rel}:{line}: {target}: an anchor into a file that is not Markdown"
                    ));
                    continue;
                }
                let defined = anchors(&std::fs::read_to_string(&dest).unwrap());
                if !defined.contains(a) {
                    problems.push(format!(
                        "{rel}:{line}: {target}: no heading with the anchor #{a}"
                    ));
                }
            }
        }
    }
    assert!(
        problems.is_empty(),
        "broken links:\n{}",
        problems.join("\n")
    );
}

/// Every page of docs/ is in the book's table of contents, and every entry there exists.
#[test]
fn the_book_lists_every_page_of_docs() {
    let root = root();
    let summary = std::fs::read_to_string(root.join("docs/SUMMARY.md")).unwrap();
    let listed: BTreeSet<String> = links(&summary)
        .into_iter()
        .map(|(_, t)| format!("docs/{}", t.split('#').next().unwrap()))
        .collect();
    let pages: BTreeSet<String> = doc_files()
        .into_iter()
        .filter(|p| p.starts_with("docs/") && p != "docs/SUMMARY.md")
        .collect();
    let missing: Vec<&String> = pages.difference(&listed).collect();
    assert!(
        missing.is_empty(),
        "pages not in docs/SUMMARY.md: {missing:?}"
    );
    for l in &listed {
        assert!(
            Path::new(&root.join(l)).is_file(),
            "SUMMARY.md lists {l}, which does not exist"
        );
    }
}

#[test]
fn the_readme_stays_short() {
    let text = std::fs::read_to_string(root().join("README.md")).unwrap();
    let n = text.lines().count();
    assert!(
        n <= 200,
        "README.md has {n} lines; the docs/ pages take the rest"
    );
}

#[test]
fn the_doc_runner_compares_outputs_as_documented() {
    let e = |v: &[&str]| v.iter().map(|s| s.to_string()).collect::<Vec<_>>();
    assert!(matches(&e(&["a", "b"]), &["a", "b"]));
    assert!(!matches(&e(&["a", "b"]), &["a", "c"]));
    assert!(!matches(&e(&["a"]), &["a", "b"]));
    assert!(matches(&e(&["a", "...", "d"]), &["a", "b", "c", "d"]));
    assert!(matches(&e(&["a", "...", "d"]), &["a", "d"]));
    assert!(!matches(&e(&["a", "...", "d"]), &["a", "b"]));
    assert!(matches(&e(&["ab..."]), &["abc"]));
    assert!(!matches(&e(&["ab..."]), &["ac"]));
    let b = blocks("x\n```sh\necho 1\n```\n\n```text\n1\n```\n  ```sh no-run\n  make\n  ```\n");
    assert_eq!(b.len(), 3);
    assert!(b[0].runs() && b[1].is_output() && !b[2].runs());
    assert_eq!(b[2].body, vec!["make".to_string()]);
    assert_eq!(
        slug("Where to put the fixture: `edbbgen place`"),
        "where-to-put-the-fixture-edbbgen-place"
    );
    assert_eq!(slug("Exit codes 0, 1 and 2"), "exit-codes-0-1-and-2");
}
