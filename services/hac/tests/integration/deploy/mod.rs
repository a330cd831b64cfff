//! The deployment files (deploy/) against the schemas they must satisfy and the binaries they
//! run:
//!
//! - every kustomize overlay renders (`kubectl kustomize`; these tests are opt-in, see
//!   [`tools_opted_in`]) and every
//!   rendered object is valid against the Kubernetes 1.32 JSON schemas vendored in
//!   deploy/schemas; the Compose files are valid against the Compose specification's schema;
//! - every flag, `HAC_*` variable and config key the manifests and Compose files use exists in
//!   the daemons' real command-line definitions (the `clap` definitions of hac-learner-service
//!   and hac-actor-service, and `hac learner --help` / `hac actor --help`), with a value they
//!   accept; the config file is accepted by the real learner;
//! - ports, probes and health checks, the config mount, the token Secret, the run directory's
//!   volume and the learner's address agree with what those settings resolve to;
//! - the image holds exactly the workspace's binaries and runs as the non-root uid the manifests
//!   expect;
//! - the daemons, started with the deploy config, serve every health service name the probes
//!   and health checks ask about.

//!
//! Modules: `binaries` (what the daemons define, and a process as a file describes it),
//! `kubernetes`, `compose`, `image`.

mod binaries;
mod compose;
mod image;
mod kubernetes;

use std::collections::{BTreeMap, BTreeSet};
use std::io::{BufRead as _, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use serde::Deserialize as _;
use serde_json::Value;

use binaries::{Daemon, check_config_table, check_config_with_learner, check_env};
use compose::{compose_files, compose_health_check, compose_validator};
use image::image_uid;
use kubernetes::{KubeSchemas, by_kind, check_kubernetes, named, probes, rendered};

pub const HAC: &str = env!("CARGO_BIN_EXE_hac");

pub fn repo() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../..")
        .canonicalize()
        .unwrap()
}

pub fn deploy() -> PathBuf {
    repo().join("deploy")
}

pub fn read(path: &Path) -> String {
    std::fs::read_to_string(path).unwrap_or_else(|e| panic!("reading {}: {e}", path.display()))
}

/// The variable that opts in to the tests that need a tool outside the Rust toolchain
/// (kubectl, docker). `.ci/run` installs the tools and sets it.
pub const TOOLS_VAR: &str = "HAC_TEST_TOOLS";

/// Whether a test that needs `tool` runs. With `HAC_TEST_TOOLS=1` it runs and a missing tool
/// fails it; otherwise it prints that it skipped and passes, so that `cargo test --workspace`
/// needs only a Rust toolchain.
pub fn tools_opted_in(test: &str, tool: &str) -> bool {
    let on = std::env::var(TOOLS_VAR).is_ok_and(|v| v == "1");
    if !on {
        eprintln!("skipped {test}: it needs {tool}; set {TOOLS_VAR}=1 to run it (.ci/run does)");
    }
    on
}

/// Fails the test with every problem found, not just the first.
fn assert_no_problems(what: &str, problems: &[String]) {
    assert!(
        problems.is_empty(),
        "{what}: {} problem(s):\n  - {}",
        problems.len(),
        problems.join("\n  - ")
    );
}

/// Every document of a YAML stream as JSON, with `<<` merge keys applied (Compose uses them).
pub fn yaml_documents(text: &str) -> Vec<Value> {
    serde_norway::Deserializer::from_str(text)
        .map(|document| {
            let mut value = serde_norway::Value::deserialize(document).expect("valid YAML");
            value.apply_merge().expect("valid YAML merge keys");
            serde_json::to_value(value).expect("YAML representable as JSON")
        })
        .filter(|value| !value.is_null())
        .collect()
}

pub fn json_file(path: &Path) -> Value {
    serde_json::from_str(&read(path)).unwrap_or_else(|e| panic!("{}: {e}", path.display()))
}

pub fn strings(value: &Value) -> Vec<String> {
    value
        .as_array()
        .map(|items| {
            items
                .iter()
                .map(|v| v.as_str().map_or_else(|| v.to_string(), str::to_string))
                .collect()
        })
        .unwrap_or_default()
}

// ---------------------------------------------------------------------------------------------
// The tests

#[test]
fn every_kustomize_overlay_renders_valid_kubernetes_objects() {
    if !tools_opted_in(
        "every_kustomize_overlay_renders_valid_kubernetes_objects",
        "kubectl",
    ) {
        return;
    }
    let mut schemas = KubeSchemas::load();
    let mut problems = Vec::new();
    for (overlay, objects) in rendered() {
        assert!(!objects.is_empty(), "{overlay} renders nothing");
        for object in objects {
            for error in schemas.validate(object) {
                problems.push(format!(
                    "{overlay}: {} {}: {error}",
                    object["kind"], object["metadata"]["name"]
                ));
            }
        }
        for kind in [
            "StatefulSet",
            "Deployment",
            "Service",
            "ConfigMap",
            "PodDisruptionBudget",
        ] {
            if by_kind(objects, kind).next().is_none() {
                problems.push(format!("{overlay}: no {kind}"));
            }
        }
    }
    assert_no_problems("schema validation", &problems);
}

#[test]
fn schema_validation_catches_a_broken_object() {
    // The validator is not vacuous: typos and wrong types in a rendered object are errors.
    if tools_opted_in(
        "schema_validation_catches_a_broken_object (Kubernetes part)",
        "kubectl",
    ) {
        let mut schemas = KubeSchemas::load();
        let (_, objects) = &rendered()[0];
        let mut object = named(objects, "StatefulSet", "hac-learner")
            .unwrap()
            .clone();
        object["spec"]["template"]["spec"]["containers"][0]["readinessProbe"]["grpc"]["port"] =
            Value::from("grpc");
        object["spec"]["template"]["spec"]["containers"][0]["imagePullPolicyy"] =
            Value::from("Always");
        let errors = schemas.validate(&object);
        assert!(errors.len() >= 2, "{errors:?}");
    }
    let mut compose = compose_files().remove(0).1;
    compose["services"]["hac-learner"]["helthcheck"] = Value::from("typo");
    assert!(!compose_validator().is_valid(&compose));
}

#[test]
fn kubernetes_manifests_agree_with_the_binaries() {
    if !tools_opted_in("kubernetes_manifests_agree_with_the_binaries", "kubectl") {
        return;
    }
    let uid = image_uid();
    let mut problems = Vec::new();
    for (overlay, objects) in rendered() {
        problems.extend(check_kubernetes(overlay, objects, uid));
    }
    assert_no_problems("Kubernetes manifests against the binaries", &problems);
}

#[test]
fn the_base_config_is_deploy_hac_toml() {
    assert_eq!(
        read(&deploy().join("k8s/base/hac.toml")),
        read(&deploy().join("hac.toml")),
        "deploy/k8s/base/hac.toml must be a copy of deploy/hac.toml (kustomize reads no file \
         outside its directory): cp deploy/hac.toml deploy/k8s/base/hac.toml"
    );
}

#[test]
fn the_config_file_is_accepted_by_both_daemons() {
    let path = deploy().join("hac.toml");
    let config: toml::Table = toml::from_str(&read(&path)).unwrap();
    let mut problems = Vec::new();
    for daemon in [Daemon::Learner, Daemon::Actor] {
        if config.get(daemon.subcommand()).is_none() {
            problems.push(format!("no [{}] table", daemon.subcommand()));
        }
        problems.extend(check_config_table(daemon, &config));
    }
    problems.extend(check_config_with_learner(&path));
    assert_no_problems("deploy/hac.toml", &problems);
}

#[test]
fn a_config_key_the_daemons_lack_is_reported() {
    // The checks fail on what the binaries do not have, so they cannot pass vacuously.
    let config: toml::Table = toml::from_str(
        "[learner]\nlisten = \"0.0.0.0:50051\"\nno_such_key = 1\n[actor]\nwindow = \"many\"\n",
    )
    .unwrap();
    let learner = check_config_table(Daemon::Learner, &config);
    assert_eq!(learner.len(), 1, "{learner:?}");
    assert!(learner[0].contains("no_such_key"), "{learner:?}");
    let actor = check_config_table(Daemon::Actor, &config);
    assert_eq!(actor.len(), 1, "{actor:?}");
    assert!(check_env(Daemon::Learner, "HAC_LISTEN", "not an address").is_err());
    assert!(check_env(Daemon::Actor, "HAC_NO_SUCH_VARIABLE", "1").is_err());
    assert!(check_env(Daemon::Learner, "HAC_LOG_FORMAT", "json").is_ok());
    assert!(check_env(Daemon::Learner, "HAC_LOG_FORMAT", "xml").is_err());
}

#[test]
fn compose_files_are_valid_against_the_compose_specification() {
    let validator = compose_validator();
    let mut problems = Vec::new();
    for (name, compose) in compose_files() {
        for error in validator.iter_errors(&compose) {
            problems.push(format!("{name}: at {}: {error}", error.instance_path()));
        }
    }
    assert_no_problems("Compose schema", &problems);
}

// ---------------------------------------------------------------------------------------------
// The daemons serve what the probes ask

/// Children killed when the test ends, however it ends.
struct Children(Vec<Child>);

impl Drop for Children {
    fn drop(&mut self) {
        for child in &mut self.0 {
            let _ = child.kill();
            let _ = child.wait();
        }
    }
}

fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port()
}

/// `hac health URL --service NAME` until SERVING or the deadline; an answer other than "not
/// reachable yet" or NOT_SERVING fails at once.
fn wait_serving(url: &str, service: &str, what: &str, deadline: Instant) -> Result<(), String> {
    loop {
        let output = Command::new(HAC)
            .args(["health", url, "--service", service])
            .output()
            .unwrap();
        if output.status.success() {
            return Ok(());
        }
        let stderr = String::from_utf8_lossy(&output.stderr).trim().to_string();
        let retry = stderr.contains("connecting to") || stderr.contains("NOT_SERVING");
        if !retry || Instant::now() > deadline {
            return Err(format!(
                "{what}: `hac health {url} --service {service:?}`: {stderr}"
            ));
        }
        std::thread::sleep(Duration::from_millis(250));
    }
}

#[test]
fn the_daemons_serve_every_probed_health_service() {
    // What the manifests and Compose files ask about.
    let mut asked: BTreeMap<Daemon, BTreeSet<String>> = BTreeMap::new();
    let manifests: &[(String, Vec<Value>)] = if tools_opted_in(
        "the_daemons_serve_every_probed_health_service (Kubernetes probes)",
        "kubectl",
    ) {
        rendered()
    } else {
        &[]
    };
    for (_, objects) in manifests {
        for workload in objects.iter().filter(|o| o["spec"]["template"].is_object()) {
            for container in workload["spec"]["template"]["spec"]["containers"]
                .as_array()
                .into_iter()
                .flatten()
            {
                let mut argv = strings(&container["command"]);
                argv.extend(strings(&container["args"]));
                if let Some((daemon, _)) = Daemon::of_command(&argv) {
                    asked
                        .entry(daemon)
                        .or_default()
                        .extend(probes(container).into_iter().map(|(_, _, s)| s));
                }
            }
        }
    }
    let (_, compose) = compose_files().remove(0);
    for service in compose["services"].as_object().unwrap().values() {
        let argv = strings(&service["command"]);
        if let (Some((daemon, _)), Ok((_, name))) = (
            Daemon::of_command(&argv),
            compose_health_check(&service["healthcheck"]["test"]),
        ) {
            asked.entry(daemon).or_default().insert(name);
        }
    }
    assert_eq!(asked.len(), 2, "{asked:?}");

    let dir = std::env::temp_dir().join(format!("hac-deploy-test-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    let token = dir.join("token");
    std::fs::write(&token, "deploy-test-token").unwrap();
    let config = deploy().join("hac.toml");
    let common = |command: &mut Command| {
        command
            .env("HAC_CONFIG", &config)
            .env("HAC_TOKEN_FILE", &token)
            // Tests bind loopback only: the file's 0.0.0.0 listeners are overridden.
            .env("HAC_METRICS_LISTEN", "127.0.0.1:0")
            .env_remove("RUST_LOG")
            .stdin(Stdio::null());
    };
    let mut children = Children(Vec::new());
    let mut learner = Command::new(HAC);
    learner
        .args(["learner", "--listen", "127.0.0.1:0", "--out"])
        .arg(dir.join("run"));
    common(&mut learner);
    let mut learner = learner
        .stdout(Stdio::piped())
        .stderr(std::fs::File::create(dir.join("learner.log")).unwrap())
        .spawn()
        .unwrap();
    let stdout = learner.stdout.take().unwrap();
    children.0.push(learner);
    let mut line = String::new();
    // Kept open until the end: the learner prints more lines (`metrics on ...`) and must not
    // meet a closed pipe.
    let mut stdout = BufReader::new(stdout);
    stdout.read_line(&mut line).unwrap();
    let Some(addr) = line.trim().strip_prefix("listening on ") else {
        panic!(
            "the learner did not start with deploy/hac.toml: {}",
            read(&dir.join("learner.log"))
        );
    };
    let learner_url = format!("http://{addr}");
    let status_port = free_port();
    let mut actor = Command::new(HAC);
    actor
        .args(["actor", "--learner", &learner_url, "--id", "deploy-test"])
        .args(["--status-listen", &format!("127.0.0.1:{status_port}")]);
    common(&mut actor);
    children.0.push(
        actor
            .stdout(Stdio::null())
            .stderr(std::fs::File::create(dir.join("actor.log")).unwrap())
            .spawn()
            .unwrap(),
    );
    let actor_url = format!("http://127.0.0.1:{status_port}");
    let mut problems = Vec::new();
    // Generous: the machine may be busy; a daemon that is up answers at once.
    let deadline = Instant::now() + Duration::from_secs(90);
    for (daemon, services) in &asked {
        let url = match daemon {
            Daemon::Learner => &learner_url,
            Daemon::Actor => &actor_url,
        };
        for service in services {
            if let Err(e) = wait_serving(url, service, daemon.binary(), deadline) {
                problems.push(e);
            }
        }
    }
    drop(children);
    drop(stdout);
    if !problems.is_empty() {
        for log in ["learner.log", "actor.log"] {
            let text = std::fs::read_to_string(dir.join(log)).unwrap_or_default();
            let tail: Vec<&str> = text.lines().rev().take(10).collect();
            problems.push(format!("{log} (last lines, newest first): {tail:#?}"));
        }
    }
    let _ = std::fs::remove_dir_all(&dir);
    assert_no_problems("health services", &problems);
}

#[test]
fn compose_files_agree_with_the_binaries() {
    assert_no_problems(
        "Compose files against the binaries",
        &compose::check_compose(),
    );
}

#[test]
fn the_image_holds_the_workspace_binaries_and_runs_as_non_root() {
    assert_no_problems("deploy/docker/Dockerfile", &image::check_image());
}
