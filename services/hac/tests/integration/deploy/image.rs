//! deploy/docker/Dockerfile, read for what it builds, copies and runs as.

use std::collections::{BTreeMap, BTreeSet};

use super::binaries::port_of;
use super::{deploy, read, repo};

#[derive(Debug)]
pub struct Dockerfile {
    stages: Vec<(String, Option<String>)>,
    build_commands: Vec<String>,
    copied_binaries: BTreeSet<String>,
    user: Option<String>,
    workdir: Option<String>,
    exposed: BTreeSet<u16>,
    rust_version: Option<String>,
}

pub fn parse_dockerfile() -> Dockerfile {
    let text = read(&deploy().join("docker/Dockerfile"));
    // Join continuation lines into instructions.
    let mut instructions = Vec::new();
    let mut current = String::new();
    for line in text.lines() {
        let trimmed = line.trim();
        if trimmed.starts_with('#') || trimmed.is_empty() {
            continue;
        }
        if let Some(head) = trimmed.strip_suffix('\\') {
            current.push_str(head);
            current.push(' ');
        } else {
            current.push_str(trimmed);
            instructions.push(std::mem::take(&mut current));
        }
    }
    let mut file = Dockerfile {
        stages: Vec::new(),
        build_commands: Vec::new(),
        copied_binaries: BTreeSet::new(),
        user: None,
        workdir: None,
        exposed: BTreeSet::new(),
        rust_version: None,
    };
    for instruction in instructions {
        let (op, rest) = instruction.split_once(' ').unwrap_or((&instruction, ""));
        let words: Vec<&str> = rest.split_whitespace().collect();
        match op.to_uppercase().as_str() {
            "ARG" => {
                if let Some(v) = rest.strip_prefix("RUST_VERSION=") {
                    file.rust_version = Some(v.to_string());
                }
            }
            "FROM" => {
                let name = words
                    .iter()
                    .position(|w| w.eq_ignore_ascii_case("as"))
                    .and_then(|i| words.get(i + 1))
                    .map(|s| s.to_string());
                file.stages.push((words[0].to_string(), name));
                file.user = None;
                file.workdir = None;
                file.copied_binaries.clear();
                file.exposed.clear();
            }
            "RUN" if rest.contains("cargo build") => file.build_commands.push(rest.to_string()),
            "COPY" => {
                let destination = words.last().copied().unwrap_or_default();
                if destination.trim_end_matches('/') == "/usr/local/bin" {
                    for source in &words[..words.len() - 1] {
                        if !source.starts_with("--") {
                            file.copied_binaries
                                .insert(source.rsplit('/').next().unwrap().to_string());
                        }
                    }
                }
            }
            "USER" => file.user = Some(rest.to_string()),
            "WORKDIR" => file.workdir = Some(rest.to_string()),
            "EXPOSE" => file.exposed.extend(
                words
                    .iter()
                    .filter_map(|p| p.split('/').next()?.parse::<u16>().ok()),
            ),
            _ => {}
        }
    }
    file
}

/// The workspace's binaries: (package, bin names) of every member with a `[[bin]]`.
pub fn workspace_binaries() -> BTreeMap<String, BTreeSet<String>> {
    let mut found = BTreeMap::new();
    for entry in std::fs::read_dir(repo().join("services")).unwrap() {
        let manifest = entry.unwrap().path().join("Cargo.toml");
        if !manifest.is_file() {
            continue;
        }
        let table: toml::Table = toml::from_str(&read(&manifest)).unwrap();
        let package = table["package"]["name"].as_str().unwrap().to_string();
        let bins: BTreeSet<String> = table
            .get("bin")
            .and_then(|b| b.as_array())
            .into_iter()
            .flatten()
            .filter_map(|b| b["name"].as_str().map(str::to_string))
            .collect();
        if !bins.is_empty() {
            found.insert(package, bins);
        }
    }
    found
}

pub fn image_uid() -> u64 {
    let user = parse_dockerfile()
        .user
        .expect("the runtime stage sets USER");
    user.split(':').next().unwrap().parse().unwrap_or_else(|_| {
        panic!("USER {user} should be numeric, so Kubernetes can check runAsNonRoot")
    })
}

pub fn check_image() -> Vec<String> {
    let file = parse_dockerfile();
    let binaries = workspace_binaries();
    let mut problems = Vec::new();
    if file.stages.len() < 2 {
        problems.push(format!(
            "expected a build and a runtime stage: {:?}",
            file.stages
        ));
    }
    let (runtime_image, _) = file.stages.last().cloned().unwrap_or_default();
    if !(runtime_image.starts_with("debian:") && runtime_image.ends_with("-slim")) {
        problems.push(format!("runtime stage {runtime_image} is not Debian slim"));
    }
    let build = file.build_commands.join(" ");
    if !build.contains("--release") || !build.contains("--locked") {
        problems.push(format!("the build should be --release --locked: {build}"));
    }
    for package in binaries.keys() {
        if !build.contains(&format!("-p {package}")) {
            problems.push(format!("the build does not build package {package}"));
        }
    }
    let expected: BTreeSet<String> = binaries.values().flatten().cloned().collect();
    if file.copied_binaries != expected {
        problems.push(format!(
            "/usr/local/bin gets {:?}, the workspace's binaries are {expected:?}",
            file.copied_binaries
        ));
    }
    for binary in ["hac", "hac-learner", "hac-actor"] {
        if !expected.contains(binary) {
            problems.push(format!("the workspace has no binary {binary}"));
        }
    }
    match file
        .user
        .as_deref()
        .map(|u| u.split(':').next().unwrap().parse::<u64>())
    {
        Some(Ok(10001)) => {}
        other => problems.push(format!(
            "USER should be the numeric uid 10001, got {other:?}"
        )),
    }
    if file.workdir.as_deref() != Some("/var/lib/hac") {
        problems.push(format!("WORKDIR {:?}, not /var/lib/hac", file.workdir));
    }
    let config: toml::Table = toml::from_str(&read(&deploy().join("hac.toml"))).unwrap();
    for (table, key) in [
        ("learner", "listen"),
        ("learner", "metrics_listen"),
        ("actor", "status_listen"),
    ] {
        let port = config[table][key].as_str().and_then(port_of);
        if !port.is_some_and(|p| file.exposed.contains(&p)) {
            problems.push(format!(
                "EXPOSE {:?} lacks [{table}] {key} port {port:?}",
                file.exposed
            ));
        }
    }
    let workspace: toml::Table = toml::from_str(&read(&repo().join("Cargo.toml"))).unwrap();
    let msrv = workspace["workspace"]["package"]["rust-version"]
        .as_str()
        .unwrap();
    let version = |v: &str| -> Vec<u32> { v.split('.').filter_map(|p| p.parse().ok()).collect() };
    match &file.rust_version {
        Some(v) if version(v) >= version(msrv) => {}
        other => problems.push(format!(
            "ARG RUST_VERSION {other:?} is older than rust-version {msrv}"
        )),
    }
    problems
}
