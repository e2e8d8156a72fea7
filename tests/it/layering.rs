//! Data flows one way, design to decoder: no stage module names a later stage, and the shared
//! modules below the stages (grid, io, image, ...) name none. Above the stages sit the
//! sweeps (`sweep`, which call the stages), then the charts (`charts`, which draw the
//! stages' results and the sweeps' results: `plotters` is named nowhere else), then the
//! commands (`pipeline`, `demo`), which run them and write their files. Read from the source,
//! so a new `use` that closes a cycle fails here with the file and the line. No source file is
//! over 1,000 lines: a longer one is split into a folder, a file per concept.

use std::collections::BTreeMap;
use std::fs;
use std::path::{Path, PathBuf};

/// The stages in the order data flows through them.
const STAGES: [&str; 6] = ["design", "fabrication", "metrology", "optics", "calibration", "decoder"];
/// Modules every stage may use; they use no stage (nor the layers above the stages).
const SHARED: [&str; 11] =
    ["error", "grid", "units", "material", "tabulated", "rng", "linalg", "io", "image", "rounding", "fft"];
/// The layers above the stages, lowest first: each names none above it.
const ABOVE: [&str; 4] = ["sweep", "charts", "pipeline", "demo"];

/// The `.rs` files of module `name`: `src/name.rs` and everything below `src/name/`.
fn sources(name: &str) -> Vec<PathBuf> {
    let src = Path::new(env!("CARGO_MANIFEST_DIR")).join("src");
    let mut files = vec![];
    let file = src.join(format!("{name}.rs"));
    if file.is_file() {
        files.push(file);
    }
    let mut dirs = vec![src.join(name)];
    while let Some(d) = dirs.pop() {
        let Ok(entries) = fs::read_dir(&d) else { continue };
        for e in entries.flatten() {
            let p = e.path();
            if p.is_dir() {
                dirs.push(p);
            } else if p.extension().is_some_and(|x| x == "rs") {
                files.push(p);
            }
        }
    }
    assert!(!files.is_empty(), "module {name} has no source under src/");
    files
}

/// Whether `line` names the module `crate::<module>` (not a longer name that starts so).
fn names(line: &str, module: &str) -> bool {
    let needle = format!("crate::{module}");
    line.match_indices(&needle).any(|(at, _)| {
        let next = line[at + needle.len()..].chars().next();
        !next.is_some_and(|c| c.is_alphanumeric() || c == '_')
    })
}

/// Lines of `name`'s sources that name `crate::<other>` for any of `others` (comments, where docs
/// link to the layers above, left out).
fn imports(name: &str, others: &[&str]) -> Vec<String> {
    let mut found = vec![];
    for file in sources(name) {
        let text = fs::read_to_string(&file).unwrap();
        for (i, line) in text.lines().enumerate() {
            if !line.trim_start().starts_with("//") && others.iter().any(|other| names(line, other)) {
                found.push(format!("{}:{}: {}", file.display(), i + 1, line.trim()));
            }
        }
    }
    found
}

#[test]
fn no_module_imports_a_later_one() {
    let mut wrong = vec![];
    for (k, stage) in STAGES.iter().enumerate() {
        let later: Vec<&str> = STAGES[k + 1..].iter().chain(&ABOVE).copied().collect();
        wrong.extend(imports(stage, &later));
    }
    for (k, layer) in ABOVE.iter().enumerate() {
        wrong.extend(imports(layer, &ABOVE[k + 1..]));
    }
    let above: Vec<&str> = STAGES.iter().chain(&ABOVE).copied().collect();
    for shared in SHARED {
        wrong.extend(imports(shared, &above));
    }
    assert!(wrong.is_empty(), "imports against the flow:\n{}", wrong.join("\n"));
}

/// The most lines a source file may hold: a longer file holds more than one concept, and is
/// split into a folder of files, each named for what it holds.
const MAX_FILE_LINES: usize = 1000;

/// The files under `src/` longer than [`MAX_FILE_LINES`], each with its line count.
fn long_files(src: &Path) -> Vec<String> {
    let (mut long, mut dirs) = (vec![], vec![src.to_path_buf()]);
    while let Some(d) = dirs.pop() {
        for p in fs::read_dir(&d).unwrap().flatten().map(|e| e.path()) {
            if p.is_dir() {
                dirs.push(p);
            } else {
                let lines = fs::read_to_string(&p).unwrap().lines().count();
                if lines > MAX_FILE_LINES {
                    long.push(format!("{}: {lines} lines", p.strip_prefix(src).unwrap().display()));
                }
            }
        }
    }
    long.sort();
    long
}

#[test]
fn no_source_file_is_over_a_thousand_lines() {
    let long = long_files(&Path::new(env!("CARGO_MANIFEST_DIR")).join("src"));
    assert!(
        long.is_empty(),
        "files over {MAX_FILE_LINES} lines (split each into a folder, a file per concept):\n{}",
        long.join("\n")
    );
}

/// The check names a file over the limit with its count, and passes one at the limit.
#[test]
fn the_length_check_names_a_long_file() {
    let dir = std::env::temp_dir().join(format!("doefab-layering-{}", std::process::id()));
    fs::create_dir_all(dir.join("a")).unwrap();
    fs::write(dir.join("a/long.rs"), "\n".repeat(MAX_FILE_LINES + 1)).unwrap();
    fs::write(dir.join("short.rs"), "\n".repeat(MAX_FILE_LINES)).unwrap();
    let long = long_files(&dir);
    fs::remove_dir_all(&dir).unwrap();
    assert_eq!(long, [format!("{}: {} lines", Path::new("a").join("long.rs").display(), MAX_FILE_LINES + 1)]);
}

/// `plotters` is named in the charts and nowhere else in the sources.
#[test]
fn only_the_charts_draw() {
    let src = Path::new(env!("CARGO_MANIFEST_DIR")).join("src");
    let (mut drawing, mut dirs) = (vec![], vec![src.clone()]);
    while let Some(d) = dirs.pop() {
        for p in fs::read_dir(&d).unwrap().flatten().map(|e| e.path()) {
            if p.is_dir() {
                dirs.push(p);
            } else if !p.starts_with(src.join("charts"))
                && fs::read_to_string(&p).unwrap().contains("plotters")
            {
                drawing.push(p.display().to_string());
            }
        }
    }
    assert!(drawing.is_empty(), "plotters named outside src/charts: {drawing:?}");
    assert!(fs::read_to_string(src.join("charts/style.rs")).unwrap().contains("plotters"));
}

#[test]
fn the_check_sees_an_import_and_not_a_longer_name() {
    // `calibration` names `optics` (earlier: allowed) and so must be seen by the scan.
    assert!(!imports("calibration", &["optics"]).is_empty());
    assert!(names("use crate::io::atomic;", "io") && names("crate::decoder}", "decoder"));
    assert!(!names("use crate::iox::a;", "io") && !names("use crate::decoders;", "decoder"));
}

/// No two files import each other, directly or around a loop, in the library (`lib.rs`) or the
/// command line (`main.rs` and `src/cli`): each strongly connected component of the file import
/// graph ([`ImportGraph`]) is one file. A failure names each cycle's files and the imports
/// between them, with the line of each.
#[test]
fn no_two_files_import_each_other() {
    let src = Path::new(env!("CARGO_MANIFEST_DIR")).join("src");
    let mut found = vec![];
    for root in ["lib.rs", "main.rs"] {
        let g = ImportGraph::read(&src, root);
        for cycle in g.cycles() {
            let edges: Vec<String> =
                g.edges_within(&cycle).iter().map(|(a, b, line)| format!("    {a}:{line} -> {b}")).collect();
            found.push(format!("{}\n{}", cycle.join(", "), edges.join("\n")));
        }
    }
    assert!(found.is_empty(), "files that import each other:\n{}", found.join("\n"));
}

/// The graph reaches every source file from the two roots and sees the imports of both crates:
/// a stage's `use crate::...`, the command line's `use cli::...` and `super::args::...`.
#[test]
fn the_import_graph_covers_the_library_and_the_command_line() {
    let src = Path::new(env!("CARGO_MANIFEST_DIR")).join("src");
    let (lib, bin) = (ImportGraph::read(&src, "lib.rs"), ImportGraph::read(&src, "main.rs"));
    let mut all = vec![];
    let mut dirs = vec![src.clone()];
    while let Some(d) = dirs.pop() {
        for p in fs::read_dir(&d).unwrap().flatten().map(|e| e.path()) {
            if p.is_dir() {
                dirs.push(p);
            } else {
                all.push(p.strip_prefix(&src).unwrap().to_string_lossy().replace('\\', "/"));
            }
        }
    }
    let mut seen: Vec<String> = lib.files.iter().chain(&bin.files).cloned().collect();
    all.sort();
    seen.sort();
    assert_eq!(all, seen);
    assert!(lib.targets("sweep/register.rs").contains(&"metrology/scan_registration/mod.rs"));
    assert!(bin.targets("main.rs").contains(&"cli/args.rs"));
    assert!(bin.targets("cli/optics.rs").iter().any(|t| t.starts_with("cli/")));
}

/// The check fails where it must: a planted cycle `a <-> b` is found, and only it; comments,
/// strings, `mod` declarations and unit-test modules are no imports; a `pub use` re-export is.
#[test]
fn the_cycle_check_sees_a_planted_cycle() {
    let mut files: BTreeMap<&str, &str> = [
        ("lib.rs", "pub mod a;\npub mod b;\npub mod c;\npub mod d;\n"),
        ("a.rs", "use crate::b::f;\npub fn g() -> u8 {\n    f()\n}\n"),
        ("b.rs", "pub fn f() -> u8 {\n    1\n}\npub fn h() -> u8 {\n    crate::a::g()\n}\n"),
        (
            "c.rs",
            "// use crate::d::x;\nuse super::a;\npub fn k() -> u8 {\n    let _ = \"crate::d::x\";\n    a::g()\n}\n\
             #[cfg(test)]\nmod tests {\n    use crate::d::x;\n}\n",
        ),
        ("d/mod.rs", "mod e;\npub use e::E;\npub fn x() {}\n"),
        ("d/e.rs", "pub struct E;\n"),
    ]
    .into_iter()
    .collect();
    let g = ImportGraph::build("lib.rs", |p| files.get(p).map(|t| t.to_string()));
    assert_eq!(g.cycles(), [["a.rs", "b.rs"]]);
    assert_eq!(g.targets("c.rs"), ["a.rs"]);
    assert_eq!(g.targets("d/mod.rs"), ["d/e.rs"]);
    assert_eq!(
        g.edges_within(&["a.rs".into(), "b.rs".into()]),
        [("a.rs".to_string(), "b.rs".to_string(), 1), ("b.rs".to_string(), "a.rs".to_string(), 5)]
    );
    // A child that uses its parent, which re-exports it: a cycle through the re-export.
    files.insert("d/e.rs", "pub struct E;\npub fn y() {\n    super::x()\n}\n");
    let g = ImportGraph::build("lib.rs", |p| files.get(p).map(|t| t.to_string()));
    assert_eq!(g.cycles(), [vec!["a.rs", "b.rs"], vec!["d/e.rs", "d/mod.rs"]]);
}

/// A token of Rust source, comments, strings, characters and lifetimes left out: a word, `::`
/// or one other character; with its line.
#[derive(Debug, Clone, Copy, PartialEq)]
enum Token<'a> {
    Word(&'a str),
    PathSep,
    Punct(char),
}

/// The tokens of `text` with their (1-based) lines.
fn tokens(text: &str) -> Vec<(Token<'_>, usize)> {
    let b = text.as_bytes();
    let (mut out, mut i, mut line) = (vec![], 0, 1);
    let word = |c: u8| c.is_ascii_alphanumeric() || c == b'_';
    // Skips to just past the first `end` from `j`, counting lines.
    let skip_to = |j: usize, end: &[u8], line: &mut usize| -> usize {
        let mut k = j;
        while k < b.len() && !b[k..].starts_with(end) {
            *line += (b[k] == b'\n') as usize;
            k += 1 + (b[k] == b'\\' && end == b"\"") as usize;
        }
        (k + end.len()).min(b.len())
    };
    while i < b.len() {
        let c = b[i];
        if c == b'\n' {
            line += 1;
            i += 1;
        } else if b[i..].starts_with(b"//") {
            while i < b.len() && b[i] != b'\n' {
                i += 1;
            }
        } else if b[i..].starts_with(b"/*") {
            let mut depth = 0;
            while i < b.len() {
                if b[i..].starts_with(b"/*") {
                    depth += 1;
                    i += 2;
                } else if b[i..].starts_with(b"*/") {
                    depth -= 1;
                    i += 2;
                    if depth == 0 {
                        break;
                    }
                } else {
                    line += (b[i] == b'\n') as usize;
                    i += 1;
                }
            }
        } else if c == b'"' {
            i = skip_to(i + 1, b"\"", &mut line);
        } else if (c == b'r' || c == b'b') && !(i > 0 && word(b[i - 1])) && raw_string(&b[i..]).is_some() {
            let (open, hashes) = raw_string(&b[i..]).unwrap_or_default();
            let end: Vec<u8> = std::iter::once(b'"').chain(std::iter::repeat_n(b'#', hashes)).collect();
            i = skip_to(i + open, &end, &mut line);
        } else if c == b'\'' {
            // A character literal ('a', '\n', '\u{..}') or a lifetime ('a).
            if b.get(i + 1) == Some(&b'\\') {
                i = skip_to(i + 2, b"'", &mut line);
            } else if b.get(i + 2) == Some(&b'\'') {
                i += 3;
            } else if let Some(n) = text[i + 1..].chars().next().filter(|ch| !ch.is_ascii()) {
                i += 1 + n.len_utf8() + 1;
            } else {
                i += 1;
                while i < b.len() && word(b[i]) {
                    i += 1;
                }
            }
        } else if word(c) {
            let start = i;
            while i < b.len() && word(b[i]) {
                i += 1;
            }
            out.push((Token::Word(&text[start..i]), line));
        } else if b[i..].starts_with(b"::") {
            out.push((Token::PathSep, line));
            i += 2;
        } else {
            let ch = text[i..].chars().next().unwrap_or(' ');
            if !ch.is_whitespace() {
                out.push((Token::Punct(ch), line));
            }
            i += ch.len_utf8();
        }
    }
    out
}

/// Where a raw (byte) string literal starts at `b`: the length of its opening (`r#"`) and its
/// count of `#`.
fn raw_string(b: &[u8]) -> Option<(usize, usize)> {
    let mut k = if b.starts_with(b"br") {
        2
    } else if b.starts_with(b"r") {
        1
    } else {
        return None;
    };
    let hashes = b[k..].iter().take_while(|&&c| c == b'#').count();
    k += hashes;
    (b.get(k) == Some(&b'"')).then_some((k + 1, hashes))
}

/// A use tree's paths from `t[*at]`, each with the name it is bound to (`as`, `self` or its
/// last segment); `*at` moves past the tree.
fn use_tree(
    t: &[(Token<'_>, usize)],
    at: &mut usize,
    prefix: &[String],
    out: &mut Vec<(Vec<String>, String)>,
) {
    let mut path = prefix.to_vec();
    loop {
        match t.get(*at).map(|x| x.0) {
            Some(Token::PathSep) => {
                *at += 1;
                continue;
            }
            Some(Token::Punct('*')) => {
                *at += 1;
                out.push((path, "*".into()));
                return;
            }
            Some(Token::Punct('{')) => {
                *at += 1;
                while !matches!(t.get(*at).map(|x| x.0), Some(Token::Punct('}')) | None) {
                    use_tree(t, at, &path, out);
                    if t.get(*at).map(|x| x.0) == Some(Token::Punct(',')) {
                        *at += 1;
                    }
                }
                *at += 1;
                return;
            }
            Some(Token::Word("self")) if !path.is_empty() => {
                *at += 1;
            }
            Some(Token::Word(w)) => {
                path.push(w.to_string());
                *at += 1;
            }
            _ => break,
        }
        if !matches!(t.get(*at).map(|x| x.0), Some(Token::PathSep)) {
            break;
        }
    }
    let mut name = path.last().cloned().unwrap_or_default();
    if t.get(*at).map(|x| x.0) == Some(Token::Word("as")) {
        if let Some(Token::Word(w)) = t.get(*at + 1).map(|x| x.0) {
            name = w.to_string();
        }
        *at += 2;
    }
    out.push((path, name));
}

/// A module of the crate: the file it is written in, its children by name, whether it is a
/// unit-test module (or inside one).
struct Module {
    file: usize,
    children: BTreeMap<String, usize>,
    test: bool,
}

/// Pass 1 of [`ImportGraph::build`]: the module tree of a crate, each declared file loaded.
struct ModuleTree {
    /// The files, relative to the source folder, and their texts.
    files: Vec<String>,
    texts: Vec<String>,
    modules: Vec<Module>,
    /// Per file: the module of each token (index into `modules`).
    at_token: Vec<Vec<usize>>,
}

impl ModuleTree {
    fn read(root: &str, read: impl Fn(&str) -> Option<String>) -> ModuleTree {
        let mut files = vec![root.to_string()];
        let mut texts = vec![read(root).unwrap_or_else(|| panic!("no crate root {root}"))];
        let mut modules = vec![Module { file: 0, children: BTreeMap::new(), test: false }];
        // Pass 1: the module tree, loading each declared file. Per file: the module of each
        // token (index into `modules`).
        let mut at_token: Vec<Vec<usize>> = vec![];
        let mut f = 0;
        while f < files.len() {
            let text = texts[f].clone();
            let toks = tokens(&text);
            let file_module = modules.iter().position(|m| m.file == f).unwrap_or(0);
            // The folder of the file's child modules: beside `lib.rs`, `main.rs`, `mod.rs`,
            // else in the folder named as the file.
            let name = files[f].clone();
            let dir = match name.rsplit_once('/') {
                _ if ["lib.rs", "main.rs", "mod.rs"]
                    .iter()
                    .any(|r| name == *r || name.ends_with(&format!("/{r}"))) =>
                {
                    name.rsplit_once('/').map_or(String::new(), |(d, _)| format!("{d}/"))
                }
                _ => format!("{}/", name.trim_end_matches(".rs")),
            };
            let (mut stack, mut depth, mut owners) = (vec![(file_module, 0usize, dir)], 0usize, vec![]);
            let mut k = 0;
            while k < toks.len() {
                owners.push(stack.last().map_or(file_module, |s| s.0));
                match toks[k].0 {
                    Token::Punct('{') => depth += 1,
                    Token::Punct('}') => {
                        if stack.len() > 1 && stack.last().is_some_and(|s| s.1 == depth) {
                            stack.pop();
                        }
                        depth = depth.saturating_sub(1);
                    }
                    Token::Word("mod") => {
                        if let (Some(Token::Word(m)), Some(next)) =
                            (toks.get(k + 1).map(|x| x.0), toks.get(k + 2).map(|x| x.0))
                        {
                            let (parent, _, dir) =
                                stack.last().cloned().unwrap_or((file_module, 0, String::new()));
                            let child = modules.len();
                            if next == Token::Punct(';') {
                                let cand = [format!("{dir}{m}.rs"), format!("{dir}{m}/mod.rs")];
                                if let Some((p, text)) =
                                    cand.iter().find_map(|p| read(p).map(|t| (p.clone(), t)))
                                {
                                    modules.push(Module {
                                        file: files.len(),
                                        children: BTreeMap::new(),
                                        test: false,
                                    });
                                    files.push(p);
                                    texts.push(text);
                                    modules[parent].children.insert(m.to_string(), child);
                                }
                            } else if next == Token::Punct('{') {
                                let test = k >= 7
                                    && toks[k - 7..k].iter().map(|t| t.0).eq([
                                        Token::Punct('#'),
                                        Token::Punct('['),
                                        Token::Word("cfg"),
                                        Token::Punct('('),
                                        Token::Word("test"),
                                        Token::Punct(')'),
                                        Token::Punct(']'),
                                    ]);
                                modules.push(Module {
                                    file: f,
                                    children: BTreeMap::new(),
                                    test: test || modules[parent].test,
                                });
                                modules[parent].children.insert(m.to_string(), child);
                                owners.push(parent);
                                owners.push(child);
                                depth += 1;
                                stack.push((child, depth, format!("{dir}{m}/")));
                                k += 3;
                                continue;
                            }
                        }
                    }
                    _ => {}
                }
                k += 1;
            }
            at_token.push(owners);
            f += 1;
        }
        ModuleTree { files, texts, modules, at_token }
    }
}

/// The file-level import graph of one crate (from its root file, `lib.rs` or `main.rs`,
/// following `mod` declarations): which file names an item of which other file, through a
/// `use` (`pub use` re-exports included) or a path in the code (`crate::a::b::f`, `super::x`,
/// a child module's `child::f`, a module a `use` brought in). A `mod` declaration is not an
/// import, and a `#[cfg(test)]` module, compiled only for the unit tests, is left out.
struct ImportGraph {
    /// The files, relative to the source folder.
    files: Vec<String>,
    /// For each file, the files it imports, each with the first line that does.
    imports: Vec<BTreeMap<usize, usize>>,
}

impl ImportGraph {
    /// The graph of the crate whose root file is `root` (relative to `src`) in the folder `src`.
    fn read(src: &Path, root: &str) -> ImportGraph {
        ImportGraph::build(root, |rel| fs::read_to_string(src.join(rel)).ok())
    }

    /// The graph of the crate whose root is the file `root`, with `read` giving a file's text by
    /// its path relative to the source folder (`None`: no such file).
    fn build(root: &str, read: impl Fn(&str) -> Option<String>) -> ImportGraph {
        let ModuleTree { files, texts, modules, at_token } = ModuleTree::read(root, read);
        // The path of each module from the root.
        let mut paths: Vec<Vec<String>> = vec![vec![]; modules.len()];
        let mut todo = vec![0];
        while let Some(m) = todo.pop() {
            for (name, &c) in &modules[m].children {
                paths[c] = [paths[m].clone(), vec![name.clone()]].concat();
                todo.push(c);
            }
        }
        // The module an absolute path reaches and whether it reached it whole.
        let walk = |path: &[String]| -> (usize, bool) {
            let mut m = 0;
            for (i, s) in path.iter().enumerate() {
                match modules[m].children.get(s) {
                    Some(&c) => m = c,
                    None => return (m, i == path.len()),
                }
            }
            (m, true)
        };
        // Pass 2: the imports.
        let mut imports = vec![BTreeMap::new(); files.len()];
        for f in 0..files.len() {
            let toks = tokens(&texts[f]);
            let owners = &at_token[f];
            // A path as written in module `m` -> absolute, or None where it names no module of
            // the crate (another crate, a type, a local).
            let resolve =
                |m: usize, segs: &[String], aliases: &BTreeMap<String, Vec<String>>| -> Option<Vec<String>> {
                    let first = segs.first()?;
                    let mut base = paths[m].clone();
                    let mut rest = segs;
                    match first.as_str() {
                        "crate" => return Some(segs[1..].to_vec()),
                        "self" => rest = &segs[1..],
                        "super" => {
                            while rest.first().is_some_and(|s| s == "super") {
                                base.pop()?;
                                rest = &rest[1..];
                            }
                        }
                        _ if modules[m].children.contains_key(first) => {}
                        _ => {
                            let a = aliases.get(first)?;
                            return Some([a.clone(), segs[1..].to_vec()].concat());
                        }
                    }
                    Some([base, rest.to_vec()].concat())
                };
            let mut aliases: BTreeMap<String, Vec<String>> = BTreeMap::new();
            let add = |to: &[String], line: usize, imports: &mut Vec<BTreeMap<usize, usize>>| {
                let target = modules[walk(to).0].file;
                if target != f {
                    imports[f].entry(target).or_insert(line);
                }
            };
            let mut k = 0;
            while k < toks.len() {
                if modules[owners[k]].test {
                    k += 1;
                    continue;
                }
                let (tok, line) = toks[k];
                let after_sep = k > 0 && toks[k - 1].0 == Token::PathSep;
                if tok == Token::Word("use") {
                    let m = owners[k];
                    let mut trees = vec![];
                    k += 1;
                    use_tree(&toks, &mut k, &[], &mut trees);
                    for (segs, name) in trees {
                        if let Some(abs) = resolve(m, &segs, &aliases) {
                            add(&abs, line, &mut imports);
                            if name != "*" && walk(&abs) == (walk(&abs).0, true) && !abs.is_empty() {
                                aliases.insert(name, abs);
                            }
                        }
                    }
                    continue;
                }
                if let (Token::Word(w), false) = (tok, after_sep) {
                    if toks.get(k + 1).map(|x| x.0) == Some(Token::PathSep)
                        && toks[k.saturating_sub(1)].0 != Token::Word("mod")
                    {
                        let mut segs = vec![w.to_string()];
                        let mut j = k + 1;
                        while toks.get(j).map(|x| x.0) == Some(Token::PathSep) {
                            match toks.get(j + 1).map(|x| x.0) {
                                Some(Token::Word(s)) => {
                                    segs.push(s.to_string());
                                    j += 2;
                                }
                                _ => break,
                            }
                        }
                        if let Some(abs) = resolve(owners[k], &segs, &aliases) {
                            add(&abs, line, &mut imports);
                        }
                        k = j;
                        continue;
                    }
                }
                k += 1;
            }
        }
        ImportGraph { files, imports }
    }

    /// The import cycles: each strongly connected component of more than one file, its files
    /// sorted.
    fn cycles(&self) -> Vec<Vec<String>> {
        let n = self.files.len();
        let reach: Vec<Vec<bool>> = (0..n)
            .map(|s| {
                let mut seen = vec![false; n];
                let mut todo = vec![s];
                while let Some(a) = todo.pop() {
                    for &b in self.imports[a].keys() {
                        if !seen[b] {
                            seen[b] = true;
                            todo.push(b);
                        }
                    }
                }
                seen
            })
            .collect();
        let mut done = vec![false; n];
        let mut out = vec![];
        for a in 0..n {
            if done[a] || !reach[a][a] {
                continue;
            }
            let mut comp: Vec<String> = (0..n)
                .filter(|&b| reach[a][b] && reach[b][a])
                .inspect(|&b| done[b] = true)
                .map(|b| self.files[b].clone())
                .collect();
            comp.sort();
            if comp.len() > 1 {
                out.push(comp);
            }
        }
        out.sort();
        out
    }

    /// The imports between the files of `cycle`: (from, to, line of `from`).
    fn edges_within(&self, cycle: &[String]) -> Vec<(String, String, usize)> {
        let inside = |i: usize| cycle.contains(&self.files[i]);
        let mut out = vec![];
        for (a, to) in self.imports.iter().enumerate().filter(|(a, _)| inside(*a)) {
            for (&b, &line) in to.iter().filter(|(b, _)| inside(**b)) {
                out.push((self.files[a].clone(), self.files[b].clone(), line));
            }
        }
        out
    }

    /// The files `file` imports.
    fn targets(&self, file: &str) -> Vec<&str> {
        let Some(f) = self.files.iter().position(|x| x == file) else { return vec![] };
        self.imports[f].keys().map(|&t| self.files[t].as_str()).collect()
    }
}
