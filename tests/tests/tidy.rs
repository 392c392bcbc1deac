//! Tidy checks that keep the workspace honest, run as ordinary tests: lints opted into,
//! dependencies pinned once, the crate layering of `docs/ARCHITECTURE.md`, no stubs, docs present,
//! conventions cited from `docs/CONVENTIONS.md` by existing headings.

use std::path::{Path, PathBuf};

use dex2hoi_tests::workspace_root;

/// The `dex2hoi-*` dependencies of each crate (docs/ARCHITECTURE.md, "Invariants"): its library
/// dependencies, then what its tests and benchmarks add. Exactly these, no more (a crate may not
/// reach past its layer, and a crate above the generator links it only into tests) and no fewer
/// (the table allows no edge that nobody uses, so it stays a true picture of the graph).
const LAYERING: [(&str, &[&str], &[&str]); 15] = [
    ("dex2hoi-repr", &[], &[]),
    ("dex2hoi-data", &["dex2hoi-repr"], &[]),
    ("dex2hoi-synth", &["dex2hoi-repr", "dex2hoi-data"], &[]),
    ("dex2hoi-import", &["dex2hoi-repr", "dex2hoi-data"], &[]),
    ("dex2hoi-model", &["dex2hoi-repr", "dex2hoi-data"], &[]),
    ("dex2hoi-diffusion", &[], &[]),
    ("dex2hoi-optim", &[], &[]),
    ("dex2hoi-plot", &[], &[]),
    ("dex2hoi-testkit", &[], &[]),
    (
        "dex2hoi-sample",
        &["dex2hoi-repr", "dex2hoi-data", "dex2hoi-model", "dex2hoi-diffusion"],
        &["dex2hoi-testkit"],
    ),
    (
        "dex2hoi-train",
        &[
            "dex2hoi-repr",
            "dex2hoi-data",
            "dex2hoi-model",
            "dex2hoi-diffusion",
            "dex2hoi-optim",
            "dex2hoi-sample",
            "dex2hoi-plot",
        ],
        &["dex2hoi-synth", "dex2hoi-testkit"],
    ),
    (
        "dex2hoi-eval",
        &[
            "dex2hoi-repr",
            "dex2hoi-data",
            "dex2hoi-model",
            "dex2hoi-diffusion",
            "dex2hoi-optim",
            "dex2hoi-sample",
        ],
        &["dex2hoi-synth"],
    ),
    (
        "dex2hoi-export",
        &["dex2hoi-repr", "dex2hoi-data", "dex2hoi-plot"],
        &["dex2hoi-synth", "dex2hoi-testkit"],
    ),
    (
        "dex2hoi-web",
        &["dex2hoi-repr", "dex2hoi-data", "dex2hoi-diffusion", "dex2hoi-sample", "dex2hoi-export"],
        &[],
    ),
    (
        "dex2hoi-cli",
        &[
            "dex2hoi-repr",
            "dex2hoi-data",
            "dex2hoi-synth",
            "dex2hoi-import",
            "dex2hoi-model",
            "dex2hoi-diffusion",
            "dex2hoi-sample",
            "dex2hoi-train",
            "dex2hoi-eval",
            "dex2hoi-export",
            "dex2hoi-plot",
        ],
        &["dex2hoi-testkit"],
    ),
];

/// Crates allowed to use `anyhow` (binaries); libraries have their own error enum.
const ANYHOW_ALLOWED: [&str; 3] = ["dex2hoi-cli", "xtask", "dex2hoi-tests"];

struct Member {
    dir: PathBuf,
    manifest: toml::Table,
}

impl Member {
    fn name(&self) -> &str {
        self.manifest["package"]["name"].as_str().expect("package.name")
    }

    fn dependency_tables(&self) -> impl Iterator<Item = (&str, &toml::Table)> {
        ["dependencies", "dev-dependencies", "build-dependencies"]
            .into_iter()
            .filter_map(|k| self.manifest.get(k).and_then(|t| t.as_table()).map(|t| (k, t)))
    }
}

fn members() -> Vec<Member> {
    let root = workspace_root();
    let mut dirs: Vec<PathBuf> = std::fs::read_dir(root.join("crates"))
        .expect("crates/")
        .map(|e| e.expect("entry").path())
        .filter(|p| p.join("Cargo.toml").is_file())
        .collect();
    dirs.sort();
    dirs.push(root.join("xtask"));
    dirs.push(root.join("tests"));
    dirs.into_iter()
        .map(|dir| {
            let text = std::fs::read_to_string(dir.join("Cargo.toml")).expect("manifest");
            Member { manifest: text.parse().expect("valid TOML"), dir }
        })
        .collect()
}

fn rust_files(dir: &Path, out: &mut Vec<PathBuf>) {
    for entry in std::fs::read_dir(dir).expect("readable dir") {
        let path = entry.expect("entry").path();
        if path.is_dir() {
            if path.file_name().is_some_and(|n| n != "target") {
                rust_files(&path, out);
            }
        } else if path.extension().is_some_and(|e| e == "rs") {
            out.push(path);
        }
    }
}

#[test]
fn every_member_opts_into_workspace_lints_and_dependencies() {
    for member in members() {
        let name = member.name().to_string();
        let lints = member.manifest.get("lints").and_then(|l| l.get("workspace"));
        assert_eq!(
            lints.and_then(|v| v.as_bool()),
            Some(true),
            "{name}: add `[lints] workspace = true`"
        );
        for (section, table) in member.dependency_tables() {
            for (dep, spec) in table {
                let pinned_once = spec.get("workspace").and_then(|v| v.as_bool()) == Some(true);
                assert!(pinned_once, "{name}: [{section}] {dep} must be `{dep}.workspace = true`");
            }
        }
    }
}

#[test]
fn crate_folders_are_named_like_their_crates() {
    for member in members() {
        if member.dir.parent().is_some_and(|p| p.ends_with("crates")) {
            let folder = member.dir.file_name().unwrap().to_string_lossy().into_owned();
            assert_eq!(folder, member.name(), "crates/{folder} holds {}", member.name());
        }
    }
}

#[test]
fn crate_dependencies_follow_the_layering() {
    for member in members() {
        let name = member.name();
        if name == "xtask" || name == "dex2hoi-tests" {
            // xtask drives cargo only; the tests crate may use every crate.
            if name == "xtask" {
                for (_, table) in member.dependency_tables() {
                    assert!(
                        table.keys().all(|k| !k.starts_with("dex2hoi")),
                        "xtask must not depend on project crates"
                    );
                }
            }
            continue;
        }
        let (_, library, tests_only) =
            LAYERING.iter().find(|(crate_name, _, _)| *crate_name == name).unwrap_or_else(|| {
                panic!("{name} is not in the layering table of tidy.rs and ARCHITECTURE.md")
            });
        let project_keys = |section: &str| -> std::collections::BTreeSet<&str> {
            member
                .dependency_tables()
                .filter(|(s, _)| *s == section)
                .flat_map(|(_, table)| table.keys().map(String::as_str))
                .filter(|k| k.starts_with("dex2hoi"))
                .collect()
        };
        let linked: std::collections::BTreeSet<&str> = project_keys("dependencies")
            .union(&project_keys("build-dependencies"))
            .copied()
            .collect();
        let dev = project_keys("dev-dependencies");
        for edge in *library {
            assert!(
                linked.contains(edge),
                "{name} does not use {edge}: remove the edge from the layering table"
            );
        }
        for edge in *tests_only {
            assert!(
                dev.contains(edge) && !linked.contains(edge),
                "{name}'s tests do not use {edge} (or its library does): fix the layering table"
            );
        }
        for dep in &linked {
            assert!(library.contains(dep), "{name} may not depend on {dep}");
        }
        for dep in &dev {
            assert!(
                library.contains(dep) || tests_only.contains(dep),
                "{name} may not depend on {dep} ([dev-dependencies])"
            );
        }
        for (section, table) in member.dependency_tables() {
            if !ANYHOW_ALLOWED.contains(&name) && section == "dependencies" {
                assert!(
                    !table.contains_key("anyhow"),
                    "{name} is a library: use its thiserror enum, not anyhow"
                );
            }
        }
    }
}

#[test]
fn architecture_doc_names_every_crate() {
    let doc = std::fs::read_to_string(workspace_root().join("docs/ARCHITECTURE.md"))
        .expect("docs/ARCHITECTURE.md");
    assert!(doc.contains("Architecture Invariant"), "ARCHITECTURE.md states its invariants");
    for member in members() {
        let name = member.name();
        if name != "dex2hoi-tests" && name != "xtask" {
            assert!(
                doc.contains(&format!("crates/{name}")),
                "docs/ARCHITECTURE.md must describe crates/{name}"
            );
        }
    }
}

/// The `.rs` files of the workspace's crates, xtask and tests.
fn workspace_rust_files(root: &Path) -> Vec<PathBuf> {
    let mut files = Vec::new();
    for dir in ["crates", "xtask", "tests"] {
        rust_files(&root.join(dir), &mut files);
    }
    files
}

#[test]
fn no_stubs_or_ignored_tests() {
    let root = workspace_root();
    let files = workspace_rust_files(&root);
    // Built from pieces so that this file does not match itself.
    let forbidden =
        [concat!("todo", "!("), concat!("unimplemented", "!("), concat!("#[", "ignore")];
    for file in files {
        let text = std::fs::read_to_string(&file).expect("readable source");
        for pattern in forbidden {
            assert!(!text.contains(pattern), "{}: contains `{pattern}`", file.display());
        }
    }
}

/// The files allowed to opt out of the workspace's denial of `unsafe`, each for one reason
/// (docs/ARCHITECTURE.md, the fused kernels' invariant): setting the variable that keeps
/// candle's elementwise operations on the calling thread, the GPU's stream and memory pool
/// settings, raw `gemm` calls, and launching the CUDA kernels of the fused optimiser, of
/// forward kinematics and of the row-wise model operations.
const UNSAFE_MODULES: [&str; 6] = [
    "crates/dex2hoi-model/src/candle_threads.rs",
    "crates/dex2hoi-model/src/cuda_device.rs",
    "crates/dex2hoi-model/src/differentiable/rows_cuda.rs",
    "crates/dex2hoi-model/src/matmul.rs",
    "crates/dex2hoi-optim/src/fused.rs",
    "crates/dex2hoi-repr/src/fk_cuda.rs",
];

#[test]
fn unsafe_stays_in_its_modules_with_a_safety_comment_per_use() {
    let root = workspace_root();
    // Built from pieces so that this file does not match itself.
    let lint = concat!("unsafe", "_code");
    // The lint itself: `deny` (or `forbid`) for the whole workspace.
    let manifest = std::fs::read_to_string(root.join("Cargo.toml")).expect("readable manifest");
    let level = manifest
        .lines()
        .find_map(|l| l.trim().strip_prefix(lint).map(|rest| rest.trim().to_owned()))
        .expect("a workspace level for the lint");
    assert!(level == "= \"deny\"" || level == "= \"forbid\"", "{lint} {level}");
    let files = workspace_rust_files(&root);
    // Any file naming the lint (allow, expect, warn, in any list or spacing).
    let mut opting_out: Vec<String> = files
        .iter()
        .filter(|f| std::fs::read_to_string(f).expect("readable source").contains(lint))
        .map(|f| f.strip_prefix(&root).expect("inside the workspace").display().to_string())
        .collect();
    opting_out.sort();
    assert_eq!(opting_out, UNSAFE_MODULES, "only {UNSAFE_MODULES:?} may name `{lint}`");
    for module in UNSAFE_MODULES {
        let text = std::fs::read_to_string(root.join(module)).expect("readable source");
        let lines: Vec<&str> = text.lines().collect();
        // Every use of the keyword outside comments: blocks, functions, impls, externs.
        let keyword = concat!("unsafe", " ");
        let keyword_braced = concat!("unsafe", "{");
        let uses: Vec<usize> = (0..lines.len())
            .filter(|&i| {
                let code = lines[i].split("//").next().unwrap_or("");
                code.contains(keyword) || code.contains(keyword_braced)
            })
            .collect();
        assert!(!uses.is_empty(), "{module}: no `unsafe` left: drop it from the list");
        for line in uses {
            let mut comment =
                lines[..line].iter().rev().take_while(|l| l.trim_start().starts_with("//"));
            assert!(
                comment.any(|l| l.trim_start().starts_with("// SAFETY:")),
                "{module}:{}: `unsafe` without a `// SAFETY:` comment right above it",
                line + 1
            );
        }
    }
}

/// The source and documentation files (`.rs`, `.md`, `.py`, `.toml`, `.sh`) that cite the
/// conventions.
const CITING_EXTENSIONS: [&str; 5] = ["rs", "md", "py", "toml", "sh"];

/// Every text file the repository holds, for the history check: the citing ones and its data.
const TEXT_EXTENSIONS: [&str; 9] = ["rs", "md", "py", "toml", "sh", "json", "yml", "yaml", "txt"];

/// The files below `dir` with one of `extensions`, outside build outputs (`target/`), hidden
/// folders and installed packages (`node_modules/`): the repository's own files.
fn text_files(dir: &Path, extensions: &[&str], out: &mut Vec<PathBuf>) {
    for entry in std::fs::read_dir(dir).expect("readable dir") {
        let path = entry.expect("entry").path();
        let name = path.file_name().and_then(|n| n.to_str()).unwrap_or_default();
        if path.is_dir() {
            if !name.starts_with('.') && name != "target" && name != "node_modules" {
                text_files(&path, extensions, out);
            }
        } else if path.extension().and_then(|e| e.to_str()).is_some_and(|e| extensions.contains(&e))
        {
            out.push(path);
        }
    }
}

#[test]
fn conventions_are_cited_from_inside_the_repository() {
    let root = workspace_root();
    let conventions =
        std::fs::read_to_string(root.join("docs/CONVENTIONS.md")).expect("docs/CONVENTIONS.md");
    let headings: Vec<&str> = conventions
        .lines()
        .filter(|l| l.starts_with('#'))
        .map(|l| l.trim_start_matches('#').trim())
        .collect();
    let mut files = vec![root.join("README.md")];
    for dir in ["crates", "docs", "xtask", "tests", "scripts", "configs"] {
        if root.join(dir).is_dir() {
            text_files(&root.join(dir), &CITING_EXTENSIONS, &mut files);
        }
    }
    // Built from pieces so that this file does not match itself.
    let outside = [concat!("REFERENCE", " section"), concat!("REFERENCE", ".md")];
    let pointer = concat!("CONVENTIONS", ".md, \"");
    let mut pointers = 0;
    for file in files {
        let text = std::fs::read_to_string(&file).expect("readable file");
        for pattern in outside {
            assert!(
                !text.contains(pattern),
                "{}: cites `{pattern}`, a document outside the repository; point at a section of \
                 docs/CONVENTIONS.md instead",
                file.display()
            );
        }
        for (at, _) in text.match_indices(pointer) {
            let rest = &text[at + pointer.len()..];
            let heading = rest.split(['"', '\n']).next().unwrap_or_default();
            assert!(
                rest[heading.len()..].starts_with('"') && headings.contains(&heading),
                "{}: cites docs/CONVENTIONS.md, \"{heading}\", which is not a heading there",
                file.display()
            );
            pointers += 1;
        }
    }
    assert!(pointers > 0, "the code cites docs/CONVENTIONS.md by heading");
}

#[test]
fn crate_roots_have_module_docs() {
    for member in members() {
        for root_file in ["src/lib.rs", "src/main.rs"] {
            let path = member.dir.join(root_file);
            if let Ok(text) = std::fs::read_to_string(&path) {
                assert!(
                    text.starts_with("//!"),
                    "{}: start with a `//!` module doc",
                    path.display()
                );
            }
        }
    }
}

#[test]
fn readme_gives_the_ci_test_command() {
    let root = workspace_root();
    let ci = std::fs::read_to_string(root.join(".ci/run")).expect(".ci/run");
    let readme = std::fs::read_to_string(root.join("README.md")).expect("README.md");
    let command = ci
        .lines()
        .map(str::trim)
        .find(|l| l.starts_with("cargo "))
        .expect(".ci/run runs a cargo command");
    assert!(
        readme.contains(command),
        "README.md must give the test command `{command}` that .ci/run runs"
    );
}

/// Where `text` names a development session by number (the word, an optional plural `s`,
/// blanks, then a digit), as 1-based line numbers.
fn development_history_lines(text: &str) -> Vec<usize> {
    // Built from pieces so that this file does not match itself.
    let word = concat!("sess", "ion");
    let mut lines = Vec::new();
    for (number, line) in text.lines().enumerate() {
        let line = line.to_lowercase();
        let mut rest = line.as_str();
        while let Some(at) = rest.find(word) {
            let after = &rest[at + word.len()..];
            let after = after.strip_prefix('s').unwrap_or(after);
            let digits = after.trim_start_matches([' ', '\t']);
            if digits.len() < after.len() && digits.starts_with(|c: char| c.is_ascii_digit()) {
                lines.push(number + 1);
                break;
            }
            rest = after;
        }
    }
    lines
}

#[test]
fn the_history_detector_finds_what_it_should() {
    let numbered = concat!("trained before sess", "ion 19");
    let plural = concat!("Sess", "ions 15-18 measured");
    assert_eq!(development_history_lines(numbered), [1]);
    assert_eq!(development_history_lines(&format!("a\n{plural}")), [2]);
    assert!(development_history_lines("a Unix process session, session-wide").is_empty());
}

/// The repository describes what dex2hoi is and does, not how it was built: no development
/// sessions named in code, docs, configs or scripts (history goes in `CHANGELOG.md`, by date).
#[test]
fn no_development_history_in_the_repository() {
    let root = workspace_root();
    let mut files = Vec::new();
    text_files(&root, &TEXT_EXTENSIONS, &mut files);
    assert!(files.iter().any(|f| f.ends_with("README.md")), "the walk reaches the root");
    let mut found = Vec::new();
    for file in files {
        let Ok(text) = std::fs::read_to_string(&file) else { continue };
        for line in development_history_lines(&text) {
            found.push(format!("{}:{line}", file.strip_prefix(&root).unwrap_or(&file).display()));
        }
    }
    assert!(found.is_empty(), "development history named in: {}", found.join(", "));
}

/// Each crate compiles its own files only: shared code lives in a crate that the others depend
/// on (`dex2hoi-testkit` for tests and benchmarks), never included by a `path` attribute.
#[test]
fn no_file_is_compiled_into_another_crate() {
    let root = workspace_root();
    // Built from pieces so that this file does not match itself.
    let attribute = concat!("#[pa", "th");
    for file in workspace_rust_files(&root) {
        let text = std::fs::read_to_string(&file).expect("readable source");
        assert!(!text.contains(attribute), "{}: includes a file by path", file.display());
    }
}

/// The top-level module a source file of a crate belongs to (`lib` for the crate root).
fn top_module(src: &Path, file: &Path) -> String {
    let relative = file.strip_prefix(src).unwrap_or(file);
    let first = relative.components().next().and_then(|c| c.as_os_str().to_str()).unwrap_or("");
    let name = first.trim_end_matches(".rs");
    if ["lib", "main", "mod"].contains(&name) { "lib".into() } else { name.into() }
}

/// The top-level modules that `text` names through `crate::` paths, outside comments
/// (`use crate::a::...`, `crate::{a, b::c}`, `crate::a::f(...)`).
fn crate_paths(text: &str) -> std::collections::BTreeSet<String> {
    let is_ident = |c: char| c.is_ascii_alphanumeric() || c == '_';
    let mut modules = std::collections::BTreeSet::new();
    for line in text.lines() {
        let code = line.split("//").next().unwrap_or("");
        let mut rest = code;
        while let Some(at) = rest.find("crate::") {
            // `dex2hoi_crate::` and the like are not this crate.
            let before = rest[..at].chars().next_back();
            rest = &rest[at + "crate::".len()..];
            if before.is_some_and(is_ident) {
                continue;
            }
            if let Some(group) = rest.strip_prefix('{') {
                let inner = group.split('}').next().unwrap_or("");
                for item in inner.split(',') {
                    let name: String = item.trim().chars().take_while(|c| is_ident(*c)).collect();
                    modules.insert(name);
                }
            } else {
                modules.insert(rest.chars().take_while(|c| is_ident(*c)).collect());
            }
        }
    }
    modules.retain(|m| !m.is_empty() && m.starts_with(|c: char| c.is_ascii_lowercase()));
    modules
}

/// A module that reaches itself through the graph's edges, with the path, if any.
fn first_cycle(
    graph: &std::collections::BTreeMap<String, std::collections::BTreeSet<String>>,
) -> Option<Vec<String>> {
    fn visit(
        node: &str,
        graph: &std::collections::BTreeMap<String, std::collections::BTreeSet<String>>,
        path: &mut Vec<String>,
        done: &mut std::collections::BTreeSet<String>,
    ) -> Option<Vec<String>> {
        if let Some(at) = path.iter().position(|n| n == node) {
            let mut cycle = path[at..].to_vec();
            cycle.push(node.to_string());
            return Some(cycle);
        }
        if done.contains(node) {
            return None;
        }
        path.push(node.to_string());
        for next in graph.get(node).into_iter().flatten() {
            if let Some(cycle) = visit(next, graph, path, done) {
                return Some(cycle);
            }
        }
        path.pop();
        done.insert(node.to_string());
        None
    }
    let mut done = std::collections::BTreeSet::new();
    graph.keys().find_map(|node| visit(node, graph, &mut Vec::new(), &mut done))
}

#[test]
fn the_cycle_finder_finds_cycles() {
    let graph = |edges: &[(&str, &str)]| {
        let mut graph =
            std::collections::BTreeMap::<String, std::collections::BTreeSet<String>>::new();
        for (from, to) in edges {
            graph.entry(from.to_string()).or_default().insert(to.to_string());
        }
        graph
    };
    assert_eq!(first_cycle(&graph(&[("a", "b"), ("b", "c"), ("a", "c")])), None);
    assert_eq!(
        first_cycle(&graph(&[("a", "b"), ("b", "c"), ("c", "a")])).map(|c| c.len()),
        Some(4)
    );
    let text = concat!(
        "use crate::{a, b::C};\n// crate::commented\nlet x = crate::c::f();\n",
        "dex2hoi_",
        "crate::d"
    );
    assert_eq!(crate_paths(text).into_iter().collect::<Vec<_>>(), ["a", "b", "c"]);
}

/// Within each crate, no top-level module imports another that imports it back, directly or
/// through others (docs/ARCHITECTURE.md, "Invariants"): what two modules share lives in a
/// module below both, so each crate's modules read in one order.
#[test]
fn no_module_imports_another_in_a_circle() {
    let root = workspace_root();
    for member in members() {
        let src = member.dir.join("src");
        if !src.is_dir() {
            continue;
        }
        let mut files = Vec::new();
        rust_files(&src, &mut files);
        let mut graph =
            std::collections::BTreeMap::<String, std::collections::BTreeSet<String>>::new();
        for file in files {
            let from = top_module(&src, &file);
            let text = std::fs::read_to_string(&file).expect("readable source");
            let edges = graph.entry(from.clone()).or_default();
            edges.extend(crate_paths(&text).into_iter().filter(|to| *to != from));
        }
        // The crate root declares and re-exports every module; it is above them all.
        graph.values_mut().for_each(|edges| {
            edges.remove("lib");
        });
        if let Some(cycle) = first_cycle(&graph) {
            let shown = member.dir.strip_prefix(&root).unwrap_or(&member.dir).display().to_string();
            panic!("{shown}: modules import each other in a circle: {}", cycle.join(" -> "));
        }
    }
}
