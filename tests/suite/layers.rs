//! The layering docs/ARCHITECTURE.md states, checked on the source: no import cycle between
//! the library's top-level modules (test code aside), and the servo imports neither the
//! station nor a transport. The library is two crates (the `omnid` crate re-exports the
//! core's modules under the same paths), read here as one source tree.

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};

/// Test-only files: they may reach up a layer to assemble what they test.
fn is_test_file(path: &Path) -> bool {
    let name = path.file_name().unwrap().to_string_lossy();
    matches!(
        name.as_ref(),
        "tests.rs" | "fake.rs" | "testkit.rs" | "testdata.rs"
    ) || name.ends_with("_tests.rs")
}

fn rust_files(path: &Path, out: &mut Vec<PathBuf>) {
    if path.is_dir() {
        for entry in std::fs::read_dir(path).unwrap() {
            rust_files(&entry.unwrap().path(), out);
        }
    } else if path.extension().is_some_and(|e| e == "rs") && !is_test_file(path) {
        out.push(path.to_path_buf());
    }
}

/// The library's source roots: the `omnid` crate's and the core's (docs/ARCHITECTURE.md,
/// Crates).
fn src_roots() -> [PathBuf; 2] {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    [root.join("src"), root.join("crates/omnid-core/src")]
}

/// Top-level module → the top-level modules its non-test code names (`crate::x`), with
/// where. A module both crates have (`cmd`) is one module.
fn imports() -> BTreeMap<String, BTreeMap<String, String>> {
    let mut modules = BTreeSet::new();
    for src in src_roots() {
        for p in std::fs::read_dir(&src).unwrap().map(|e| e.unwrap().path()) {
            let m = p.file_stem().unwrap().to_string_lossy().into_owned();
            if (p.is_dir() || p.extension().is_some_and(|e| e == "rs")) && m != "lib" && m != "main"
            {
                modules.insert(m);
            }
        }
    }
    let mut graph = BTreeMap::new();
    for m in &modules {
        let mut files = Vec::new();
        for src in src_roots() {
            let dir = src.join(m);
            if dir.is_dir() {
                rust_files(&dir, &mut files);
            } else if src.join(format!("{m}.rs")).is_file() {
                files.push(src.join(format!("{m}.rs")));
            }
        }
        let mut uses = BTreeMap::new();
        for f in files {
            let text = std::fs::read_to_string(&f).unwrap();
            // A file's own unit tests come last.
            let code = text.split("#[cfg(test)]\nmod tests").next().unwrap();
            for (n, line) in code.lines().enumerate() {
                if line.trim_start().starts_with("//") {
                    continue;
                }
                for part in line.split("crate::").skip(1) {
                    let target: String = part
                        .chars()
                        .take_while(|c| c.is_ascii_alphanumeric() || *c == '_')
                        .collect();
                    if &target != m && modules.contains(&target) {
                        uses.entry(target)
                            .or_insert_with(|| format!("{}:{}", f.display(), n + 1));
                    }
                }
            }
        }
        graph.insert(m.clone(), uses);
    }
    graph
}

#[test]
fn no_import_cycle_between_top_level_modules() {
    let graph = imports();
    assert!(graph.len() > 10, "modules found: {:?}", graph.keys());
    let edges: BTreeMap<&String, Vec<&String>> = graph
        .iter()
        .map(|(m, uses)| (m, uses.keys().collect()))
        .collect();
    if let Some(cycle) = find_cycle(&edges) {
        let steps: Vec<String> = cycle
            .windows(2)
            .map(|w| format!("{} -> {} ({})", w[0], w[1], graph[*w[0]][*w[1]]))
            .collect();
        panic!("import cycle:\n{}", steps.join("\n"));
    }
}

/// A cycle in `edges` (its first node repeated at the end), if there is one: depth-first, a
/// node met again while still on the path closes it.
fn find_cycle<K: Ord>(edges: &BTreeMap<K, Vec<K>>) -> Option<Vec<&K>> {
    fn visit<'a, K: Ord>(
        n: &'a K,
        edges: &'a BTreeMap<K, Vec<K>>,
        done: &mut BTreeMap<&'a K, bool>,
        path: &mut Vec<&'a K>,
    ) -> Option<Vec<&'a K>> {
        match done.get(n) {
            Some(true) => return None,
            Some(false) => {
                let from = path.iter().position(|p| *p == n).unwrap();
                let mut cycle = path[from..].to_vec();
                cycle.push(n);
                return Some(cycle);
            }
            None => {}
        }
        done.insert(n, false);
        path.push(n);
        for next in edges.get(n).into_iter().flatten() {
            if let Some(c) = visit(next, edges, done, path) {
                return Some(c);
            }
        }
        path.pop();
        done.insert(n, true);
        None
    }
    let mut done = BTreeMap::new();
    edges
        .keys()
        .find_map(|n| visit(n, edges, &mut done, &mut Vec::new()))
}

#[test]
fn the_servo_imports_neither_the_station_nor_a_transport() {
    let graph = imports();
    for above in ["station", "transport", "cmd"] {
        assert!(
            !graph["servo"].contains_key(above),
            "servo uses {above} at {}",
            graph["servo"][above]
        );
    }
    for above in ["transport", "cmd"] {
        assert!(
            !graph["station"].contains_key(above),
            "station uses {above} at {}",
            graph["station"][above]
        );
    }
}

/// The module path of a source file under `src/` (`transport/zenoh/port.rs` → `transport`,
/// `zenoh`, `port`; a `mod.rs` is its folder).
fn module_path(src: &Path, file: &Path) -> Vec<String> {
    let rel = file.strip_prefix(src).unwrap().with_extension("");
    let mut segs: Vec<String> = rel
        .components()
        .map(|c| c.as_os_str().to_string_lossy().into_owned())
        .collect();
    if segs.last().is_some_and(|s| s == "mod") {
        segs.pop();
    }
    segs
}

/// The file, in either crate, that defines the longest prefix of module path `segs` that is
/// a file.
fn file_of(segs: &[String]) -> Option<PathBuf> {
    for n in (1..=segs.len()).rev() {
        for src in src_roots() {
            let base = segs[..n].iter().fold(src.clone(), |p, s| p.join(s));
            for candidate in [base.with_extension("rs"), base.join("mod.rs")] {
                if candidate.is_file() && !is_test_file(&candidate) {
                    return Some(candidate);
                }
            }
        }
    }
    None
}

/// File → the other files of the library its non-test code names through `crate::` and
/// `super::` paths (a child's items named without either are not seen), with where.
fn file_imports() -> BTreeMap<PathBuf, BTreeMap<PathBuf, String>> {
    let mut files = Vec::new();
    for src in src_roots() {
        let mut found = Vec::new();
        rust_files(&src, &mut found);
        found.retain(|f| {
            let name = f.file_name().unwrap();
            name != "main.rs" && !f.starts_with(src.join("cli"))
        });
        files.extend(found.into_iter().map(|f| (src.clone(), f)));
    }
    let mut graph = BTreeMap::new();
    for (src, f) in &files {
        let own = module_path(src, f);
        let text = std::fs::read_to_string(f).unwrap();
        let code = text.split("#[cfg(test)]").next().unwrap();
        let mut uses = BTreeMap::new();
        for (n, line) in code.lines().enumerate() {
            let t = line.trim_start();
            if t.starts_with("//") || t.starts_with("pub mod") || t.starts_with("mod ") {
                continue;
            }
            let mut targets = Vec::new();
            for part in line.split("crate::").skip(1) {
                targets.push(path_segments(part));
            }
            // `super::super::x` from `a/b/c.rs` (module a::b::c) is a::x.
            let mut rest = line;
            while let Some(k) = rest.find("super::") {
                let before = &rest[..k];
                if before.ends_with("super::") || before.ends_with(char::is_alphanumeric) {
                    rest = &rest[k + 7..];
                    continue;
                }
                let mut tail = &rest[k..];
                let mut up = 0;
                while let Some(t) = tail.strip_prefix("super::") {
                    up += 1;
                    tail = t;
                }
                let mut segs: Vec<String> = own[..own.len().saturating_sub(up)].to_vec();
                segs.extend(path_segments(tail));
                targets.push(segs);
                rest = tail;
            }
            for segs in targets {
                if let Some(to) = file_of(&segs) {
                    if &to != f {
                        uses.entry(to)
                            .or_insert_with(|| format!("{}:{}", f.display(), n + 1));
                    }
                }
            }
        }
        graph.insert(f.clone(), uses);
    }
    graph
}

/// The module names at the start of a path (`zenoh::door::Door` → zenoh, door, Door).
fn path_segments(part: &str) -> Vec<String> {
    let mut segs = Vec::new();
    for seg in part.split("::") {
        let name: String = seg
            .chars()
            .take_while(|c| c.is_ascii_alphanumeric() || *c == '_')
            .collect();
        if name.is_empty() {
            break;
        }
        let whole = name.len() == seg.len();
        segs.push(name);
        if !whole {
            break;
        }
    }
    segs
}

/// Inside `transport` each file uses only the layers below its own (docs/ARCHITECTURE.md's
/// table), and no port uses another: the Unix socket and zenoh are ports of the station's
/// host, and a third transport touches neither.
#[test]
fn transport_files_keep_the_order_the_architecture_states() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let doc = std::fs::read_to_string(root.join("docs/ARCHITECTURE.md")).unwrap();
    let table = doc
        .split("Inside `transport` the files keep this order")
        .nth(1)
        .expect("docs/ARCHITECTURE.md states the transport's file order");
    // Rows top to bottom: each names its files or folders in backticks.
    let rows: Vec<Vec<String>> = table
        .lines()
        .skip_while(|l| !l.starts_with('|'))
        .take_while(|l| l.starts_with('|'))
        .skip(2)
        .map(|l| {
            let cells: Vec<&str> = l.split('|').collect();
            cells[2]
                .split('`')
                .skip(1)
                .step_by(2)
                .map(String::from)
                .collect()
        })
        .collect();
    assert!(rows.len() >= 4, "rows: {rows:?}");
    let dir = root.join("src/transport");
    // A file's layer: the row naming it, or the most specific folder naming it.
    let layer = |f: &Path| -> usize {
        let rel = f.strip_prefix(&dir).unwrap().to_string_lossy().into_owned();
        let mut best: Option<(usize, usize)> = None;
        for (k, row) in rows.iter().enumerate() {
            for name in row {
                let hit = if name.ends_with('/') {
                    rel.starts_with(name.as_str())
                } else {
                    &rel == name
                };
                let len = if name.ends_with('/') {
                    name.len()
                } else {
                    usize::MAX
                };
                if hit && best.is_none_or(|(_, l)| len > l) {
                    best = Some((k, len));
                }
            }
        }
        best.unwrap_or_else(|| panic!("{rel} is in no row of the transport's table"))
            .0
    };
    let graph = file_imports();
    let mut checked = 0;
    for (f, uses) in graph.iter().filter(|(f, _)| f.starts_with(&dir)) {
        let from = layer(f);
        for (to, at) in uses.iter().filter(|(t, _)| t.starts_with(&dir)) {
            let below = layer(to);
            assert!(
                below > from || (below == from && from != 0),
                "{} (layer {from}) uses {} (layer {below}) at {at}",
                f.display(),
                to.display()
            );
            checked += 1;
        }
    }
    assert!(checked > 20, "only {checked} uses seen");
}

/// No two files of the library use each other through a longer or shorter circle, except
/// through a folder's `mod.rs` (the folder's shared vocabulary, which names its children).
#[test]
fn no_import_cycle_between_files() {
    let graph = file_imports();
    let is_mod = |p: &Path| {
        p.file_name()
            .is_some_and(|n| n == "mod.rs" || n == "lib.rs")
    };
    let edges: BTreeMap<&PathBuf, Vec<&PathBuf>> = graph
        .iter()
        .map(|(f, uses)| {
            (
                f,
                uses.keys().filter(|t| !is_mod(t) && !is_mod(f)).collect(),
            )
        })
        .collect();
    if let Some(cycle) = find_cycle(&edges) {
        let steps: Vec<String> = cycle
            .windows(2)
            .map(|w| {
                let (from, to) = (*w[0], *w[1]);
                format!(
                    "{} -> {} ({})",
                    from.display(),
                    to.display(),
                    graph[from][to]
                )
            })
            .collect();
        panic!("import cycle between files:\n{}", steps.join("\n"));
    }
}

/// The core crate — most of the tests — links none of the network and plotting stacks
/// (docs/ARCHITECTURE.md, Crates): neither it nor the path crates it uses name them.
#[test]
fn the_core_links_no_network_or_plotting_stack() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let heavy = ["zenoh", "tokio", "foxglove", "plotters"];
    let mut manifests = vec![root.join("crates/omnid-core/Cargo.toml")];
    let mut seen = 0;
    while let Some(manifest) = manifests.pop() {
        let text = std::fs::read_to_string(&manifest).unwrap();
        let doc: toml::Table = toml::from_str(&text).unwrap();
        let deps = doc["dependencies"].as_table().unwrap();
        for (name, spec) in deps {
            assert!(
                !heavy.iter().any(|h| name.contains(h)),
                "{} depends on {name}",
                manifest.display()
            );
            if let Some(path) = spec.get("path").and_then(|p| p.as_str()) {
                manifests.push(manifest.parent().unwrap().join(path).join("Cargo.toml"));
            }
            seen += 1;
        }
    }
    assert!(seen > 10, "only {seen} dependencies read");
}
