//! The project's Markdown documents link to each other, to sections of each other and to files
//! of the repository (plots, examples, deploy files). Every such link must lead somewhere: the
//! file must exist and, for a `#section` of a Markdown file, one of its headings must have that
//! anchor (GitHub's rule: lower case, punctuation dropped, spaces to hyphens, `-1`, `-2` for
//! repeats). Links with a scheme (`https:`, `mailto:`) are not followed.

use std::collections::{HashMap, HashSet};
use std::path::{Path, PathBuf};

use crate::deploy::{read, repo};

/// Every Markdown file of the repository outside build output, run directories and hidden ones.
fn markdown_files(dir: &Path, out: &mut Vec<PathBuf>) {
    let mut entries: Vec<_> = std::fs::read_dir(dir)
        .unwrap_or_else(|e| panic!("listing {}: {e}", dir.display()))
        .map(|e| e.unwrap().path())
        .collect();
    entries.sort();
    for path in entries {
        let name = path.file_name().unwrap().to_string_lossy();
        if name.starts_with('.') || name == "target" || name == "runs" {
            continue;
        }
        if path.is_dir() {
            markdown_files(&path, out);
        } else if name.ends_with(".md") {
            out.push(path);
        }
    }
}

/// The lines of a Markdown text outside fenced code blocks, with their numbers from 1.
fn prose_lines(text: &str) -> impl Iterator<Item = (usize, &str)> {
    let mut fenced = false;
    text.lines().enumerate().filter_map(move |(i, line)| {
        if line.trim_start().starts_with("```") {
            fenced = !fenced;
            return None;
        }
        (!fenced).then_some((i + 1, line))
    })
}

/// GitHub's anchor for a heading's text.
fn slug(heading: &str) -> String {
    heading
        .trim()
        .to_lowercase()
        .chars()
        .filter(|c| c.is_alphanumeric() || matches!(c, '-' | '_' | ' '))
        .map(|c| if c == ' ' { '-' } else { c })
        .collect()
}

/// The anchors of a Markdown text's headings.
fn anchors(text: &str) -> HashSet<String> {
    let mut seen: HashSet<String> = HashSet::new();
    for (_, line) in prose_lines(text) {
        let hashes = line.chars().take_while(|&c| c == '#').count();
        if !(1..=6).contains(&hashes) || !line[hashes..].starts_with(' ') {
            continue;
        }
        let base = slug(&line[hashes..]);
        let mut anchor = base.clone();
        let mut n = 0;
        while seen.contains(&anchor) {
            n += 1;
            anchor = format!("{base}-{n}");
        }
        seen.insert(anchor);
    }
    seen
}

/// The link targets of a line (`[text](target)` and `![alt](target)`), outside inline code.
fn link_targets(line: &str) -> Vec<&str> {
    let mut targets = Vec::new();
    for (k, part) in line.split('`').enumerate() {
        if k % 2 == 1 {
            continue; // inside an inline code span
        }
        let mut rest = part;
        while let Some(at) = rest.find("](") {
            rest = &rest[at + 2..];
            let end = rest.find([')', ' ']).unwrap_or(rest.len());
            targets.push(&rest[..end]);
            rest = &rest[end..];
        }
    }
    targets
}

#[test]
fn every_link_in_the_documents_leads_to_a_file_and_a_heading_that_exist() {
    let root = repo();
    let mut files = Vec::new();
    markdown_files(&root, &mut files);
    assert!(
        files.iter().any(|f| f.ends_with("docs/RESULTS.md")),
        "the walk found no docs/RESULTS.md under {}",
        root.display()
    );
    let mut checked = 0;
    let mut broken = Vec::new();
    // Each linked Markdown file's anchors, read once (by its canonical path).
    let mut anchors_of: HashMap<PathBuf, HashSet<String>> = HashMap::new();
    for file in &files {
        let text = read(file);
        for (number, line) in prose_lines(&text) {
            for target in link_targets(line) {
                if target.is_empty() || target.contains("://") || target.starts_with("mailto:") {
                    continue;
                }
                checked += 1;
                let (path, anchor) = target.split_once('#').unwrap_or((target, ""));
                let linked = if path.is_empty() {
                    file.clone()
                } else {
                    file.parent().unwrap().join(path)
                };
                let at = format!("{}:{number}", file.strip_prefix(&root).unwrap().display());
                if !linked.exists() {
                    broken.push(format!("{at}: {target}: no such file"));
                } else if !anchor.is_empty()
                    && linked.extension().is_some_and(|e| e == "md")
                    && !anchors_of
                        .entry(linked.canonicalize().unwrap())
                        .or_insert_with_key(|path| anchors(&read(path)))
                        .contains(anchor)
                {
                    broken.push(format!("{at}: {target}: no heading with this anchor"));
                }
            }
        }
    }
    assert!(
        checked > 100,
        "only {checked} links found: the scan is broken"
    );
    assert!(broken.is_empty(), "broken links:\n{}", broken.join("\n"));
}

#[test]
fn anchors_follow_githubs_rule() {
    let text = "# Results\n## HAC against HIRO, 2 levels (the paper's Figure 4)\n\
                ```sh\n# not a heading\n```\n## 3 > 2 > 1: `hac bench`\n## Results\n";
    let got = anchors(text);
    for want in [
        "results",
        "hac-against-hiro-2-levels-the-papers-figure-4",
        "3--2--1-hac-bench",
        "results-1",
    ] {
        assert!(got.contains(want), "{want} missing from {got:?}");
    }
    assert!(!got.contains("not-a-heading"));
    assert_eq!(
        link_targets("see [a](docs/A.md#x), `[b](c)` and ![p](img/p.svg \"title\")"),
        ["docs/A.md#x", "img/p.svg"]
    );
}
