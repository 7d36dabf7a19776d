//! Architecture invariants checked on the source: no module imports another in a circle (the
//! code map in ARCHITECTURE.md is a layering, not a web).

use crate::common::*;
use std::collections::{BTreeMap, BTreeSet};

/// Top-level module → the top-level modules its code (not its comments or tests) names as
/// `crate::module`.
fn imports() -> BTreeMap<String, BTreeSet<String>> {
    let src = root().join("src");
    let mut modules = BTreeSet::new();
    for e in std::fs::read_dir(&src).unwrap() {
        let name = e.unwrap().file_name().to_string_lossy().into_owned();
        let m = name.trim_end_matches(".rs").to_string();
        if m != "main" && m != "lib" {
            modules.insert(m);
        }
    }
    let mut graph: BTreeMap<String, BTreeSet<String>> = BTreeMap::new();
    let mut stack = vec![src.clone()];
    while let Some(dir) = stack.pop() {
        for e in std::fs::read_dir(&dir).unwrap() {
            let path = e.unwrap().path();
            if path.is_dir() {
                stack.push(path);
                continue;
            }
            if path.extension().is_none_or(|x| x != "rs") {
                continue;
            }
            let rel = path.strip_prefix(&src).unwrap();
            let top = rel
                .components()
                .next()
                .unwrap()
                .as_os_str()
                .to_string_lossy()
                .trim_end_matches(".rs")
                .to_string();
            if !modules.contains(&top) {
                continue;
            }
            let text = std::fs::read_to_string(&path).unwrap();
            let code = text.split("#[cfg(test)]").next().unwrap_or("");
            for line in code.lines() {
                let l = line.trim_start();
                if l.starts_with("//") {
                    continue;
                }
                let l = l.split("//").next().unwrap_or("");
                for part in l.split("crate::").skip(1) {
                    let dep: String = part
                        .chars()
                        .take_while(|c| c.is_ascii_alphanumeric() || *c == '_')
                        .collect();
                    if dep != top && modules.contains(&dep) {
                        graph.entry(top.clone()).or_default().insert(dep);
                    }
                }
            }
        }
    }
    graph
}

#[test]
fn no_module_imports_in_a_circle() {
    let g = imports();
    // Depth-first search for a back edge; report the circle.
    fn visit(
        n: &str,
        g: &BTreeMap<String, BTreeSet<String>>,
        path: &mut Vec<String>,
        done: &mut BTreeSet<String>,
    ) -> Option<Vec<String>> {
        if let Some(k) = path.iter().position(|p| p == n) {
            let mut c = path[k..].to_vec();
            c.push(n.to_string());
            return Some(c);
        }
        if done.contains(n) {
            return None;
        }
        path.push(n.to_string());
        for d in g.get(n).into_iter().flatten() {
            if let Some(c) = visit(d, g, path, done) {
                return Some(c);
            }
        }
        path.pop();
        done.insert(n.to_string());
        None
    }
    let mut done = BTreeSet::new();
    for m in g.keys() {
        let circle = visit(m, &g, &mut Vec::new(), &mut done);
        assert!(
            circle.is_none(),
            "import circle: {}",
            circle.unwrap().join(" -> ")
        );
    }
    // The check itself sees imports: the cell file's module depends on the controller's.
    assert!(g["cell"].contains("controller"), "{g:?}");
    assert!(
        !g["cell"].contains("pipeline"),
        "cell takes nothing from pipeline"
    );
}

/// The compiler's stages: what the code map's "never depend on a stage" rules name.
const STAGES: &[&str] = &[
    "sample", "select", "order", "safety", "pipeline", "emit", "verify",
];

/// The layering rules of the code map (ARCHITECTURE.md, each module's **Never:** line), as
/// (module, what it must not import, the rule's words).
fn never_rules() -> Vec<(&'static str, Vec<&'static str>, &'static str)> {
    let stages_and = |more: &[&'static str]| -> Vec<&'static str> {
        STAGES.iter().chain(more).copied().collect()
    };
    vec![
        (
            "units",
            stages_and(&["robot", "model", "cell", "cli", "report"]),
            "the base of everything",
        ),
        (
            "robot",
            stages_and(&["cell", "calibrate", "twin", "diagnose", "report", "cli"]),
            "depend on later stages",
        ),
        (
            "model",
            stages_and(&["cell", "calibrate", "twin", "report", "cli"]),
            "the model is the robot's, not a stage's",
        ),
        (
            "controller",
            stages_and(&["cell"]),
            "depend on the cell module or any stage",
        ),
        ("timing", STAGES.to_vec(), "depend on a stage"),
        (
            "cell",
            STAGES.to_vec(),
            "know about stages (it imports nothing from the pipeline)",
        ),
        (
            "calibrate",
            vec!["pipeline", "report", "cli"],
            "import `pipeline` (the pipeline imports `calibrate::predict`)",
        ),
        (
            "compensate",
            vec!["pipeline", "report", "cli"],
            "import `pipeline`, `report` or `cli`",
        ),
        (
            "plot",
            vec!["report", "cli", "pipeline"],
            "figures from numbers, no reports or stages",
        ),
    ]
}

#[test]
fn the_layering_the_code_map_states_holds() {
    let graph = imports();
    let map = std::fs::read_to_string(root().join("ARCHITECTURE.md")).unwrap();
    let mut broken = Vec::new();
    for (module, forbidden, rule) in never_rules() {
        let src = root().join("src");
        assert!(
            src.join(module).is_dir() || src.join(format!("{module}.rs")).is_file(),
            "{module}: no such module"
        );
        let deps = graph.get(module).cloned().unwrap_or_default();
        for dep in forbidden {
            if deps.contains(dep) {
                broken.push(format!(
                    "{module} imports {dep}: the code map says never {rule}"
                ));
            }
        }
    }
    // Nothing but the binary imports the command line; only the command line and nothing in
    // the library renders a report page.
    for (module, deps) in &graph {
        if module != "cli" && deps.contains("cli") {
            broken.push(format!("{module} imports cli"));
        }
        if !matches!(module.as_str(), "cli" | "report") && deps.contains("report") {
            broken.push(format!(
                "{module} imports report (pages are drawn by the CLI's call)"
            ));
        }
    }
    // The rules quoted from the code map are still in it.
    for rule in [
        "depend on the cell module or any stage",
        "import `pipeline`, `report` or `cli`",
    ] {
        assert!(map.contains(rule), "ARCHITECTURE.md no longer says: {rule}");
    }
    assert!(broken.is_empty(), "{}", broken.join("\n"));
    // The check can fail: a graph with a forbidden edge is caught.
    assert!(graph
        .get("pipeline")
        .is_some_and(|d| d.contains("calibrate")));
}

/// Every `.rs` file under `dir`, at any depth.
fn rust_files(dir: &std::path::Path) -> Vec<std::path::PathBuf> {
    let mut out = Vec::new();
    let mut stack = vec![dir.to_path_buf()];
    while let Some(dir) = stack.pop() {
        for e in std::fs::read_dir(&dir).unwrap() {
            let path = e.unwrap().path();
            if path.is_dir() {
                stack.push(path);
            } else if path.extension().is_some_and(|x| x == "rs") {
                out.push(path);
            }
        }
    }
    out
}

/// The code outside `src/dialect/` (not its tests), file by file.
fn code_outside_dialects() -> Vec<(std::path::PathBuf, String)> {
    let dialects = root().join("src/dialect");
    rust_files(&root().join("src"))
        .into_iter()
        .filter(|p| !p.starts_with(&dialects))
        .map(|path| {
            let text = std::fs::read_to_string(&path).unwrap();
            let code = text.split("#[cfg(test)]").next().unwrap_or("").to_string();
            (path, code)
        })
        .collect()
}

#[test]
fn a_dialect_is_known_in_its_folder_only() {
    // The dialects take nothing from the stages that write, rewrite or check programs.
    let g = imports();
    for dep in ["compensate", "emit", "verify", "pipeline", "cli"] {
        assert!(
            !g.get("dialect").is_some_and(|d| d.contains(dep)),
            "dialect imports {dep}"
        );
    }
    // No code outside src/dialect/ chooses by a dialect's name: a match arm or a comparison
    // with a registered name is controller knowledge outside its folder.
    let names = edbbgen::dialect::names();
    assert_eq!(names.len(), 6, "{names:?}");
    for (path, code) in code_outside_dialects() {
        for name in &names {
            for form in [
                format!("\"{name}\" =>"),
                format!("\"{name}\" |"),
                format!("Some(\"{name}\")"),
                format!("== \"{name}\""),
            ] {
                assert!(
                    !code.contains(&form),
                    "{} chooses by the dialect name: {form}",
                    path.display()
                );
            }
        }
    }
    // compensate rewrites a program through its reader's positions: it has no tokenizer.
    let program = std::fs::read_to_string(root().join("src/compensate/program.rs")).unwrap();
    let program = program.split("#[cfg(test)]").next().unwrap_or("");
    for scan in [
        ".find(",
        ".rfind(",
        "split_whitespace",
        "char_indices",
        ".as_bytes()",
    ] {
        assert!(
            !program.contains(scan),
            "src/compensate/program.rs looks into the text: {scan}"
        );
    }
}

#[test]
fn a_subcommand_imports_no_other_subcommand() {
    // The command line is two layers: the subcommands' files (`*_cli.rs`) over the helpers they
    // share (`mod.rs`, `common.rs`, `progress.rs`, `logruns.rs`, `args.rs`). A subcommand takes
    // nothing from another; a helper takes nothing from a subcommand.
    let dir = root().join("src/cli");
    let mut files: Vec<(String, String)> = Vec::new();
    for e in std::fs::read_dir(&dir).unwrap() {
        let path = e.unwrap().path();
        if path.extension().is_some_and(|x| x == "rs") {
            let name = path.file_stem().unwrap().to_string_lossy().into_owned();
            let text = std::fs::read_to_string(&path).unwrap();
            let code = text.split("#[cfg(test)]").next().unwrap_or("").to_string();
            files.push((name, code));
        }
    }
    let subcommands: Vec<&str> = files
        .iter()
        .map(|(n, _)| n.as_str())
        .filter(|n| n.ends_with("_cli"))
        .collect();
    assert!(subcommands.len() >= 8, "{subcommands:?}");
    for (name, code) in &files {
        let code: String = code
            .lines()
            .filter(|l| !l.trim_start().starts_with("//"))
            .map(|l| l.split("//").next().unwrap_or("").to_string() + "\n")
            .collect();
        for other in &subcommands {
            if other == name || name == "mod" {
                continue;
            }
            for form in [
                format!("super::{other}"),
                format!("cli::{other}"),
                format!("{{{other}"),
                format!(" {other},"),
                format!(" {other}}}"),
            ] {
                assert!(
                    !code.contains(&form),
                    "src/cli/{name}.rs imports the subcommand {other} ({form}): move what they share to the library or cli/common.rs"
                );
            }
        }
    }
}

/// The longest a function in src/ may be: lines from its `fn` to its closing brace.
const MAX_FN_LINES: usize = 150;

/// Every function with a body (free, in an impl, a trait's default) in `text`: (line of its
/// `fn`, name, lines from the `fn` to the closing brace). Parsed, so braces in strings, chars
/// and comments do not count.
fn function_lengths(text: &str) -> Vec<(usize, String, usize)> {
    use syn::visit::Visit;
    struct Lengths(Vec<(usize, String, usize)>);
    impl Lengths {
        fn note(&mut self, sig: &syn::Signature, block: &syn::Block) {
            let from = sig.fn_token.span.start().line;
            let to = block.brace_token.span.close().end().line;
            self.0.push((from, sig.ident.to_string(), to + 1 - from));
        }
    }
    impl<'ast> Visit<'ast> for Lengths {
        fn visit_item_fn(&mut self, f: &'ast syn::ItemFn) {
            self.note(&f.sig, &f.block);
            syn::visit::visit_item_fn(self, f);
        }
        fn visit_impl_item_fn(&mut self, f: &'ast syn::ImplItemFn) {
            self.note(&f.sig, &f.block);
            syn::visit::visit_impl_item_fn(self, f);
        }
        fn visit_trait_item_fn(&mut self, f: &'ast syn::TraitItemFn) {
            if let Some(block) = &f.default {
                self.note(&f.sig, block);
            }
            syn::visit::visit_trait_item_fn(self, f);
        }
    }
    let file = syn::parse_file(text).unwrap_or_else(|e| panic!("not Rust: {e}"));
    let mut lengths = Lengths(Vec::new());
    lengths.visit_file(&file);
    lengths.0
}

#[test]
fn no_function_in_src_is_over_150_lines() {
    // The measure itself: braces in strings, raw strings, chars and comments are not code.
    let sample = "fn a() {\n    let s = \"{{\";\n    let r = r#\"}\"#;\n    let c = '{';\n    // }\n}\n\nimpl X {\n    fn b(&self) -> u8 {\n        1\n    }\n}\n\ntrait T {\n    fn c() {}\n    fn d();\n}\n";
    assert_eq!(
        function_lengths(sample),
        [
            (1, "a".to_string(), 6),
            (9, "b".to_string(), 3),
            (15, "c".to_string(), 1)
        ]
    );

    let mut lengths = Vec::new();
    for path in rust_files(&root().join("src")) {
        let text = std::fs::read_to_string(&path).unwrap();
        let rel = path.strip_prefix(root()).unwrap();
        let file = rel.to_string_lossy().replace('\\', "/");
        for (line, name, n) in function_lengths(&text) {
            lengths.push((file.clone(), line, name, n));
        }
    }
    lengths.sort();
    assert!(lengths.len() > 1000, "{} functions in src/", lengths.len());
    let mut offenders = Vec::new();
    for (file, line, name, n) in &lengths {
        if *n > MAX_FN_LINES {
            offenders.push(format!("{file}:{line} {name} {n} lines"));
        }
    }
    assert!(
        offenders.is_empty(),
        "functions over {MAX_FN_LINES} lines (split them at their steps into named functions):\n{}",
        offenders.join("\n")
    );
}

/// The command line parses, calls the library and prints: no file of it but the flag
/// definitions (`args.rs`) grows past 400 lines.
#[test]
fn no_command_line_file_but_args_is_over_400_lines() {
    let mut long = Vec::new();
    for e in std::fs::read_dir(root().join("src/cli")).unwrap() {
        let path = e.unwrap().path();
        let name = path.file_name().unwrap().to_string_lossy().into_owned();
        if name == "args.rs" || path.extension().is_none_or(|x| x != "rs") {
            continue;
        }
        let n = std::fs::read_to_string(&path).unwrap().lines().count();
        if n > 400 {
            long.push(format!("src/cli/{name}: {n} lines"));
        }
    }
    assert!(
        long.is_empty(),
        "move domain logic to the library:\n{}",
        long.join("\n")
    );
}
