//! The README and the guide: every relative link and image in `README.md`, `CHANGELOG.md` and
//! `docs/*.md` points at a file that exists, and an anchor into a Markdown file at one of its
//! headings (GitHub's slugs); the README stays a short front page that opens with the two
//! set-up commands and links into the guide. Read from the source tree, so a page moved or a
//! heading renamed fails here with the file and the link.

use std::collections::BTreeSet;
use std::fs;
use std::path::{Path, PathBuf};

/// The README's most lines.
const README_MAX_LINES: usize = 250;
/// The fewest guide pages (`docs/*.md`) the README links to.
const README_MIN_GUIDE_PAGES: usize = 6;

fn root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

/// `README.md`, `CHANGELOG.md` and every `docs/*.md`.
fn markdown_files() -> Vec<PathBuf> {
    let root = root();
    let mut files = vec![root.join("README.md"), root.join("CHANGELOG.md")];
    let mut guide: Vec<PathBuf> = fs::read_dir(root.join("docs"))
        .expect("docs/ is readable")
        .flatten()
        .map(|e| e.path())
        .filter(|p| p.extension().is_some_and(|x| x == "md"))
        .collect();
    guide.sort();
    files.extend(guide);
    files
}

fn read(path: &Path) -> String {
    fs::read_to_string(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()))
}

/// The lines outside fenced code blocks (numbered from 1): what Markdown renders as prose,
/// headings, tables and links.
fn prose_lines(text: &str) -> Vec<(usize, &str)> {
    let mut lines = vec![];
    let mut fence: Option<&str> = None;
    for (i, line) in text.lines().enumerate() {
        let trimmed = line.trim_start();
        let marker = ["```", "~~~"].into_iter().find(|m| trimmed.starts_with(m));
        match (fence, marker) {
            (None, Some(m)) => fence = Some(m),
            (Some(f), Some(m)) if f == m => fence = None,
            (None, None) => lines.push((i + 1, line)),
            _ => {}
        }
    }
    lines
}

/// `line` with every inline code span (`` `...` ``) replaced by spaces.
fn blank_code_spans(line: &str) -> String {
    let mut out = String::with_capacity(line.len());
    let mut in_code = false;
    for c in line.chars() {
        if c == '`' {
            in_code = !in_code;
            out.push(' ');
        } else {
            out.push(if in_code { ' ' } else { c });
        }
    }
    out
}

/// The targets of the links and images `[text](target)` / `![alt](target)` on a line: the part
/// in parentheses after a closing bracket, without angle brackets or a title.
fn link_targets(line: &str) -> Vec<String> {
    let mut targets = vec![];
    let mut rest = line;
    while let Some(at) = rest.find("](") {
        let after = &rest[at + 2..];
        let Some(end) = closing_paren(after) else { break };
        let inner = after[..end].trim();
        let target = inner.split_whitespace().next().unwrap_or("");
        let target = target.trim_start_matches('<').trim_end_matches('>');
        if !target.is_empty() {
            targets.push(target.to_string());
        }
        rest = &after[end..];
    }
    targets
}

/// Where the parenthesis opened before `s` closes (nested pairs allowed, as in file names).
fn closing_paren(s: &str) -> Option<usize> {
    let mut depth = 0usize;
    for (i, c) in s.char_indices() {
        match c {
            '(' => depth += 1,
            ')' if depth == 0 => return Some(i),
            ')' => depth -= 1,
            _ => {}
        }
    }
    None
}

fn is_url(target: &str) -> bool {
    ["http:", "https:", "mailto:"].iter().any(|scheme| target.starts_with(scheme))
}

/// GitHub's anchor for a heading's text: lower case, inline markup and punctuation dropped
/// (letters, digits, `-` and `_` kept), spaces turned into hyphens.
fn slug(heading: &str) -> String {
    let text = heading.replace(['`', '*'], "");
    // Link text stays, its target goes: "[a](b)" reads "a".
    let mut plain = String::new();
    let mut rest = text.as_str();
    while let Some(open) = rest.find('[') {
        plain.push_str(&rest[..open]);
        let after = &rest[open + 1..];
        match (after.find("]("), after.find(']')) {
            (Some(close), Some(first)) if close == first => {
                plain.push_str(&after[..close]);
                let tail = &after[close + 2..];
                rest = closing_paren(tail).map_or(tail, |end| &tail[end + 1..]);
            }
            _ => {
                plain.push('[');
                rest = after;
            }
        }
    }
    plain.push_str(rest);
    plain
        .trim()
        .to_lowercase()
        .chars()
        .filter_map(|c| match c {
            ' ' => Some('-'),
            c if c.is_alphanumeric() || c == '-' || c == '_' => Some(c),
            _ => None,
        })
        .collect()
}

/// The anchors of a Markdown file's headings, the repeats numbered as GitHub numbers them.
fn anchors(text: &str) -> BTreeSet<String> {
    let mut found = BTreeSet::new();
    for (_, line) in prose_lines(text) {
        let hashes = line.chars().take_while(|&c| c == '#').count();
        if !(1..=6).contains(&hashes) || !line[hashes..].starts_with(' ') {
            continue;
        }
        let base = slug(line[hashes..].trim().trim_end_matches('#'));
        let mut anchor = base.clone();
        let mut n = 0;
        while found.contains(&anchor) {
            n += 1;
            anchor = format!("{base}-{n}");
        }
        found.insert(anchor);
    }
    found
}

/// Every broken relative link of `file`, as `file:line: target (why)`.
fn broken_links(file: &Path) -> Vec<String> {
    let text = read(file);
    let dir = file.parent().unwrap();
    let name = file.strip_prefix(root()).unwrap_or(file).display().to_string();
    let mut broken = vec![];
    for (number, line) in prose_lines(&text) {
        for target in link_targets(&blank_code_spans(line)) {
            if is_url(&target) {
                continue;
            }
            let (path, anchor) = match target.split_once('#') {
                Some((path, anchor)) => (path, Some(anchor)),
                None => (target.as_str(), None),
            };
            let linked = if path.is_empty() { file.to_path_buf() } else { dir.join(path) };
            if !linked.exists() {
                broken.push(format!("{name}:{number}: {target} (no file {path})"));
                continue;
            }
            let Some(anchor) = anchor else { continue };
            if linked.extension().is_some_and(|x| x == "md") && !anchors(&read(&linked)).contains(anchor) {
                broken.push(format!("{name}:{number}: {target} (no heading #{anchor} in {path})"));
            }
        }
    }
    broken
}

#[test]
fn every_relative_link_of_the_readme_and_the_guide_resolves() {
    let files = markdown_files();
    assert!(files.len() >= 2 + README_MIN_GUIDE_PAGES, "guide pages missing: {files:?}");
    let broken: Vec<String> = files.iter().flat_map(|f| broken_links(f)).collect();
    assert!(broken.is_empty(), "broken links:\n{}", broken.join("\n"));
}

#[test]
fn the_readme_is_a_short_front_page_into_the_guide() {
    let text = read(&root().join("README.md"));
    let lines = text.lines().count();
    assert!(lines <= README_MAX_LINES, "README.md: {lines} lines, at most {README_MAX_LINES}");

    let first_block: String = text.split("```").nth(1).expect("README.md: no code block").to_string();
    for command in ["cargo run --release -- demo", "cargo test --release"] {
        assert!(
            first_block.contains(command),
            "README.md: the first code block does not hold `{command}`:\n{first_block}"
        );
    }

    let pages: BTreeSet<String> = prose_lines(&text)
        .iter()
        .flat_map(|(_, line)| link_targets(&blank_code_spans(line)))
        .map(|t| t.split('#').next().unwrap_or("").to_string())
        .filter(|t| t.starts_with("docs/") && t.ends_with(".md"))
        .collect();
    assert!(
        pages.len() >= README_MIN_GUIDE_PAGES,
        "README.md links {} guide pages under docs/, at least {README_MIN_GUIDE_PAGES}: {pages:?}",
        pages.len()
    );
}

#[test]
fn slugs_follow_github() {
    assert_eq!(slug("Speed against accuracy: `bench fab`"), "speed-against-accuracy-bench-fab");
    assert_eq!(
        slug("A decoder for the paper's element: `built-in:doefab-measured-psf`"),
        "a-decoder-for-the-papers-element-built-indoefab-measured-psf"
    );
    assert_eq!(slug("JSON, progress and `--quiet`"), "json-progress-and---quiet");
    assert_eq!(slug("2026-11-28"), "2026-11-28");
    assert_eq!(slug("See [the guide](docs/README.md) now"), "see-the-guide-now");
    let repeated = anchors("# Also\n\n## Also\n\n```sh\n# not a heading\n```\n");
    assert_eq!(repeated, ["also", "also-1"].map(String::from).into_iter().collect());
    assert_eq!(
        link_targets("![a](x.png) and [b](y.md#z \"title\") but `[c](no.md)`"),
        ["x.png", "y.md#z", "no.md"].map(String::from)
    );
    assert_eq!(link_targets(&blank_code_spans("[b](y.md) but `[c](no.md)`")), ["y.md".to_string()]);
}
