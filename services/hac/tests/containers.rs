//! The Compose stack for real: the image built here with no registry
//! (deploy/docker/build-local.sh), deploy/compose.yaml and deploy/compose.shm.yaml brought up
//! with Docker Compose, and the faults a cluster meets, one after the other on one stack
//! (learner, trainers, evaluator; `hac status` from the host, `/metrics` on the published port):
//!
//! - scale 2 -> 1 -> 4 -> 1 -> 2 trainers while training, with no error in the learner's log;
//! - node loss: an actor's process killed with SIGKILL; Compose restarts the container and the
//!   actor registers with a new incarnation, ingesting within [`ACTOR_BACK`] of its restart;
//! - partition: an actor's container disconnected from the stack's network for [`PARTITION`],
//!   then reconnected: the learner sees it silent, then back under the same incarnation; stopped
//!   with SIGTERM, the actor sent exactly what the learner stored from it (its resends refused as
//!   duplicates);
//! - rolling restart: the learner stopped with SIGTERM (drained, final checkpoint); every actor
//!   gets the final weights and stops cleanly, Compose starts it again, and it ingests again once
//!   the learner is started;
//! - learner loss: the learner's process killed with SIGKILL; Compose restarts it, it resumes
//!   from its newest checkpoint on the volume (versions and counts continue) and every actor
//!   ingests again within [`LEARNER_BACK`] of the kill, under the same incarnation;
//!
//! then the accounting: every actor, stopped with SIGTERM, sent exactly what it had acknowledged
//! as durable and what the learner stored from its incarnation; no trainer was ever renumbered
//! (a restarted learner lacking something it acknowledged would renumber it); the learner's log
//! has no error. A second stack runs a trainer over shared memory, and a third trains pendulum
//! (2 levels) to 90 % with 8 trainers.
//!
//! Opt-in (`HAC_TEST_TOOLS=1`, set by `.ci/run`): it needs docker, `docker compose` v2, root and
//! debootstrap (for the base image, unless `hac-base:bookworm` is there). Every stack has its
//! own Compose project name, ports and scratch directory, and everything the test creates
//! (containers, networks, volumes, the image and its own tag of the base image) is removed when
//! it ends, passing or failing. Each scenario prints its figures.

use std::io::{Read as _, Write as _};
use std::path::{Path, PathBuf};
use std::process::{Command, Output};
use std::time::{Duration, Instant};

use serde_json::Value;

mod common;

const HAC: &str = env!("CARGO_BIN_EXE_hac");
/// An actor's container restarted by Compose is registered and ingesting within this.
const ACTOR_BACK: Duration = Duration::from_secs(5);
/// After a learner's container is killed: the learner answers again and every actor ingests
/// again within this.
const LEARNER_BACK: Duration = Duration::from_secs(30);
const PARTITION: Duration = Duration::from_secs(30);
/// The learner's message for an actor it has not heard from for this long: gone.
const GONE: f64 = 10.0;

fn repo() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../..")
        .canonicalize()
        .unwrap()
}

/// Runs `command`; its stdout, or a panic with what it printed.
fn run(command: &mut Command) -> String {
    let output = command
        .output()
        .unwrap_or_else(|e| panic!("{command:?}: {e}"));
    check(command, output)
}

fn check(command: &Command, output: Output) -> String {
    assert!(
        output.status.success(),
        "{command:?} failed ({}):\n{}\n{}",
        output.status,
        String::from_utf8_lossy(&output.stdout),
        String::from_utf8_lossy(&output.stderr)
    );
    String::from_utf8(output.stdout).unwrap()
}

/// SIGKILL to a container's main process from the host, as the kernel's OOM killer or a crash
/// would end it (`docker kill` counts as a deliberate stop, after which Docker restarts nothing).
fn crash(container: &str) {
    let pid = inspect(container, "{{.State.Pid}}");
    assert!(
        pid.parse::<u32>().is_ok_and(|p| p > 0),
        "{container}: pid {pid}"
    );
    run(Command::new("kill").args(["-KILL", &pid]));
}

/// The `summary.json` of the run in the learner container `learner` (copied out through a
/// scratch directory named `name`).
fn learner_summary(learner: &str, name: &str) -> Value {
    let out = common::scratch("hac-containers-test", name);
    docker(&[
        "cp",
        &format!("{learner}:/var/lib/hac/run/summary.json"),
        out.to_str().unwrap(),
    ]);
    let summary = common::summary(&out);
    let _ = std::fs::remove_dir_all(&out);
    summary
}

fn docker(args: &[&str]) -> String {
    run(Command::new("docker").args(args))
}

/// A container's log (the daemons log to stderr, which `docker logs` gives on its stderr).
fn container_log(container: &str) -> String {
    let output = Command::new("docker")
        .args(["logs", container])
        .output()
        .unwrap();
    assert!(output.status.success(), "docker logs {container}");
    String::from_utf8_lossy(&output.stdout).into_owned() + &String::from_utf8_lossy(&output.stderr)
}

/// `docker inspect -f <format> <container>`, trimmed.
fn inspect(container: &str, format: &str) -> String {
    docker(&["inspect", "-f", format, container])
        .trim()
        .to_string()
}

fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port()
}

/// Polls `probe` every 100 ms until it gives a value; panics with `context()` after `limit`.
fn wait_for<T>(
    what: &str,
    limit: Duration,
    context: impl Fn() -> String,
    mut probe: impl FnMut() -> Option<T>,
) -> (T, Duration) {
    let started = Instant::now();
    loop {
        if let Some(value) = probe() {
            return (value, started.elapsed());
        }
        assert!(
            started.elapsed() < limit,
            "{what}: not within {limit:?}\n{}",
            context()
        );
        std::thread::sleep(Duration::from_millis(100));
    }
}

// ---------------------------------------------------------------------------------------------
// The image

/// The image the test built and the base it built on, under this process's own tags: removed on
/// drop.
struct Image {
    tag: String,
    base: String,
}

impl Drop for Image {
    fn drop(&mut self) {
        for image in [&self.tag, &self.base] {
            let _ = Command::new("docker")
                .args(["image", "rm", "--force", image])
                .output();
        }
    }
}

fn build_image() -> Image {
    let tag = format!("hac-cluster-test-{}:latest", std::process::id());
    // The base under a tag of this process's own, so that test processes sharing a Docker engine
    // never remove the base another one is building on: the shared `hac-base:bookworm` tagged
    // again when it is there (removing a second tag leaves the image and its other tags), else
    // imported by build-local.sh under this tag alone.
    let shared = "hac-base:bookworm";
    let base = format!("hac-base:test-{}", std::process::id());
    let had_base = Command::new("docker")
        .args(["image", "inspect", shared])
        .output()
        .unwrap()
        .status
        .success();
    if had_base {
        run(Command::new("docker").args(["tag", shared, &base]));
    }
    let image = Image {
        tag: tag.clone(),
        base: base.clone(),
    };
    let started = Instant::now();
    let output = run(Command::new(repo().join("deploy/docker/build-local.sh"))
        .env("HAC_IMAGE", &tag)
        .env("HAC_BASE_IMAGE", &base));
    eprint!("{output}");
    eprintln!(
        "image: {tag} built in {:.1} s (base {})",
        started.elapsed().as_secs_f64(),
        if had_base { "present" } else { "imported" }
    );
    image
}

// ---------------------------------------------------------------------------------------------
// A Compose stack

/// One Compose project: the deploy files copied as they are into a scratch directory (with a
/// token and, for the fault tests, an override of the run), its own name and host ports. Down
/// with its volumes on drop.
struct Stack {
    name: String,
    dir: PathBuf,
    files: Vec<&'static str>,
    image: String,
    grpc: u16,
    metrics: u16,
}

impl Stack {
    fn new(label: &str, files: &[&'static str], image: &Image, run_override: Option<&str>) -> Self {
        let name = format!("hac-test-{}-{label}", std::process::id());
        let dir = common::scratch("hac-containers-test", label);
        for file in ["compose.yaml", "compose.shm.yaml", "hac.toml"] {
            std::fs::copy(repo().join("deploy").join(file), dir.join(file)).unwrap();
        }
        std::fs::create_dir_all(dir.join("secrets")).unwrap();
        // Readable by the containers' uid (the secret is bind-mounted as it is).
        std::fs::write(dir.join("secrets/hac_token"), "containers-test-token\n").unwrap();
        let mut files = files.to_vec();
        if let Some(text) = run_override {
            std::fs::write(dir.join("test.yaml"), text).unwrap();
            files.push("test.yaml");
        }
        if run_override == Some(FAULT_RUN) {
            // A stop rate cannot be unset by a variable: the run's copy of the file goes without.
            let config = std::fs::read_to_string(dir.join("hac.toml")).unwrap();
            let endless: Vec<&str> = config
                .lines()
                .filter(|l| !l.starts_with("stop_at ="))
                .collect();
            assert_eq!(endless.len() + 1, config.lines().count(), "{config}");
            std::fs::write(dir.join("hac.toml"), endless.join("\n") + "\n").unwrap();
        }
        Stack {
            name,
            dir,
            files,
            image: image.tag.clone(),
            grpc: free_port(),
            metrics: free_port(),
        }
    }

    fn compose(&self) -> Command {
        let mut command = Command::new("docker");
        command
            .args([
                "compose",
                "--project-name",
                &self.name,
                "--project-directory",
            ])
            .arg(&self.dir);
        for file in &self.files {
            command.arg("--file").arg(self.dir.join(file));
        }
        command
            .env("HAC_IMAGE", &self.image)
            .env("HAC_PUBLISH_ADDR", "127.0.0.1")
            .env("HAC_GRPC_PORT", self.grpc.to_string())
            .env("HAC_METRICS_PORT", self.metrics.to_string());
        command
    }

    fn run(&self, args: &[&str]) -> String {
        run(self.compose().args(args))
    }

    /// `up -d` with the image as it is: never pulled, never built.
    fn up(&self, trainers: usize) {
        self.run(&[
            "up",
            "--detach",
            "--no-build",
            "--pull",
            "never",
            "--no-recreate",
            "--scale",
            &format!("hac-actor={trainers}"),
        ]);
    }

    /// The ids of a service's running containers.
    fn containers(&self, service: &str) -> Vec<String> {
        self.run(&["ps", "--quiet", service])
            .lines()
            .map(str::to_string)
            .collect()
    }

    fn learner_container(&self) -> String {
        let mut ids = self.run(&["ps", "--quiet", "--all", "hac-learner"]);
        ids.truncate(ids.trim_end().len());
        assert!(!ids.is_empty() && !ids.contains('\n'), "{ids:?}");
        ids
    }

    /// The logs of every container of a service, stopped ones included.
    fn logs(&self, service: &str) -> String {
        self.run(&["ps", "--quiet", "--all", service])
            .lines()
            .map(container_log)
            .collect()
    }

    /// The last lines of every service's log, for failure messages.
    fn tails(&self) -> String {
        let output = self
            .compose()
            .args(["logs", "--no-color", "--tail", "25"])
            .output()
            .unwrap();
        String::from_utf8_lossy(&output.stdout).into_owned()
    }

    fn learner_url(&self) -> String {
        format!("http://127.0.0.1:{}", self.grpc)
    }

    /// The learner's status (`hac status --json` from the host), `None` while it does not answer.
    fn status(&self) -> Option<Value> {
        let output = Command::new(HAC)
            .args(["status", "--learner", &self.learner_url(), "--json"])
            .args(["--timeout", "2", "--token-file"])
            .arg(self.dir.join("secrets/hac_token"))
            .output()
            .ok()?;
        if !output.status.success() {
            return None;
        }
        let value: Value = serde_json::from_slice(&output.stdout).ok()?;
        Some(value["learner"].clone())
    }

    /// An actor's own status, asked inside its container.
    fn actor_status(&self, container: &str) -> Value {
        let text = docker(&[
            "exec",
            container,
            "hac",
            "status",
            "--actor",
            "http://127.0.0.1:50052",
            "--json",
            "--token-file",
            "/run/secrets/hac_token",
        ]);
        serde_json::from_str::<Value>(&text).unwrap()["actor"].clone()
    }
}

impl Drop for Stack {
    fn drop(&mut self) {
        let _ = self
            .compose()
            .args(["down", "--volumes", "--remove-orphans", "--timeout", "10"])
            .output();
        let _ = std::fs::remove_dir_all(&self.dir);
    }
}

// ---------------------------------------------------------------------------------------------
// Reading the learner's status

fn u(value: &Value, key: &str) -> u64 {
    value[key]
        .as_u64()
        .unwrap_or_else(|| panic!("no {key} in {value}"))
}

fn actors(status: &Value) -> Vec<Value> {
    status["actors"].as_array().cloned().unwrap_or_default()
}

/// The learner's entry of the actor in `container`. The actor's id is `<hostname>-<pid>`: the
/// container id's first 12 digits and 1, which a restarted container keeps.
fn entry(status: &Value, container: &str) -> Option<Value> {
    let id = format!("{}-", &container[..12]);
    actors(status)
        .into_iter()
        .find(|a| a["actor_id"].as_str().is_some_and(|a| a.starts_with(&id)))
}

/// A container's host name (the start of its actors' ids), for the figures.
fn actor_id(container: &str) -> String {
    inspect(container, "{{.Config.Hostname}}")
}

/// Each container's (incarnation, stored_through) on the learner, if every one is there.
fn stored(stack: &Stack, containers: &[String]) -> Option<Vec<(u64, u64)>> {
    let status = stack.status()?;
    containers
        .iter()
        .map(|c| entry(&status, c).map(|a| (u(&a, "incarnation"), u(&a, "stored_through"))))
        .collect()
}

/// Waits until every container's actor stored beyond `above` (same order: under the same
/// incarnation, or anything under a new one); how long it took.
fn ingesting_beyond(
    stack: &Stack,
    containers: &[String],
    above: &[(u64, u64)],
    limit: Duration,
) -> Duration {
    wait_for(
        "the actors ingesting again",
        limit,
        || stack.tails(),
        || {
            let now = stored(stack, containers)?;
            now.iter()
                .zip(above)
                .all(|(n, a)| (n.0 == a.0 && n.1 > a.1) || (n.0 != a.0 && n.1 > 0))
                .then_some(())
        },
    )
    .1
}

/// Lines of a JSON log at level ERROR.
fn errors(log: &str) -> Vec<&str> {
    log.lines()
        .filter(|l| l.contains("\"level\":\"ERROR\""))
        .collect()
}

/// The first JSON log line whose message is `message`, parsed.
fn log_event(log: &str, message: &str) -> Vec<Value> {
    log.lines()
        .filter_map(|l| serde_json::from_str::<Value>(l).ok())
        .filter(|v| v["fields"]["message"] == message)
        .collect()
}

/// GET http://127.0.0.1:<port>/metrics.
fn metrics(port: u16) -> String {
    let mut stream = std::net::TcpStream::connect(("127.0.0.1", port)).unwrap();
    stream
        .set_read_timeout(Some(Duration::from_secs(10)))
        .unwrap();
    stream
        .write_all(b"GET /metrics HTTP/1.0\r\nHost: 127.0.0.1\r\n\r\n")
        .unwrap();
    let mut text = String::new();
    stream.read_to_string(&mut text).unwrap();
    text
}

// ---------------------------------------------------------------------------------------------
// The scenarios

/// The fault tests' run: deploy/hac.toml's, except that it does not end while they run (no
/// stop rate, a large episode budget), with checkpoints every 5 s.
const FAULT_RUN: &str = r#"services:
  hac-learner:
    environment:
      HAC_EPISODES: "10000000"
      HAC_CHECKPOINT_EVERY: "5"
"#;

/// The eight-trainer run: episode turns, and a budget far beyond the episodes to 90 % (the run
/// stops there): embedded pendulum runs reach 90 % in 150-700 episodes, but 1 seed in 10 did
/// not within 1000 (docs/RESULTS.md), and a test must not fail on a slow seed.
const EIGHT_RUN: &str = r#"services:
  hac-learner:
    environment:
      HAC_EPISODES_IN_FLIGHT: "1"
      HAC_EPISODES: "3000"
"#;

fn bring_up(stack: &Stack, trainers: usize) -> Vec<String> {
    let started = Instant::now();
    stack.up(trainers);
    let learner = stack.learner_container();
    let (_, healthy) = wait_for(
        "the learner healthy",
        Duration::from_secs(120),
        || stack.tails(),
        || (inspect(&learner, "{{.State.Health.Status}}") == "healthy").then_some(()),
    );
    let containers = stack.containers("hac-actor");
    assert_eq!(containers.len(), trainers, "{containers:?}");
    let evaluator = stack.containers("hac-evaluator");
    assert_eq!(evaluator.len(), 1, "{evaluator:?}");
    let zero = vec![(0, 0); trainers];
    ingesting_beyond(stack, &containers, &zero, Duration::from_secs(120));
    let status = stack.status().unwrap();
    let roles: Vec<&str> = status["actors"]
        .as_array()
        .unwrap()
        .iter()
        .map(|a| a["role"].as_str().unwrap())
        .collect();
    assert_eq!(
        roles.iter().filter(|r| r.contains("evaluator")).count(),
        1,
        "{status}"
    );
    assert!(entry(&status, &evaluator[0]).is_some(), "{status}");
    for container in containers.iter().chain(&evaluator) {
        wait_for(
            "an actor healthy",
            Duration::from_secs(90),
            || stack.tails(),
            || (inspect(container, "{{.State.Health.Status}}") == "healthy").then_some(()),
        );
    }
    eprintln!(
        "up: learner healthy after {:.1} s, {trainers} trainers and the evaluator ingesting and healthy after {:.1} s",
        healthy.as_secs_f64(),
        started.elapsed().as_secs_f64()
    );
    containers
}

fn node_loss(stack: &Stack, victim: &str) {
    let before = entry(&stack.status().unwrap(), victim).unwrap();
    let pid = inspect(victim, "{{.State.Pid}}");
    crash(victim);
    let killed = Instant::now();
    // The restart as seen from here: the first poll that finds a new main process running (the
    // poll's own delay, tens of milliseconds, makes the time from restart to back look shorter
    // by at most that).
    let ((), restarted) = wait_for(
        "the killed actor restarted by Compose",
        Duration::from_secs(60),
        || stack.tails(),
        || {
            let now = inspect(victim, "{{.State.Running}} {{.State.Pid}}");
            (now.starts_with("true ") && now != format!("true {pid}")).then_some(())
        },
    );
    let (after, back) = wait_for(
        "the restarted actor registered and ingesting",
        Duration::from_secs(60),
        || stack.tails(),
        || {
            let a = entry(&stack.status()?, victim)?;
            (u(&a, "incarnation") != u(&before, "incarnation") && u(&a, "stored_through") > 0)
                .then_some(a)
        },
    );
    eprintln!(
        "node loss: {} killed (SIGKILL); restarted by Compose {:.2} s after the kill; incarnation {} -> {}; registered and ingesting {:.2} s after its restart ({:.2} s after the kill)",
        actor_id(victim),
        restarted.as_secs_f64(),
        u(&before, "incarnation"),
        u(&after, "incarnation"),
        back.as_secs_f64(),
        killed.elapsed().as_secs_f64(),
    );
    assert!(
        u(&after, "incarnation") > u(&before, "incarnation"),
        "{before} {after}"
    );
    assert!(
        back < ACTOR_BACK,
        "the restarted actor took {back:?}\n{}",
        stack.tails()
    );
}

fn partition(stack: &Stack, victim: &str) {
    let network = format!("{}_default", stack.name);
    let before = entry(&stack.status().unwrap(), victim).unwrap();
    docker(&["network", "disconnect", &network, victim]);
    let cut = Instant::now();
    let mut gone_for: f64 = 0.0;
    while cut.elapsed() < PARTITION {
        if let Some(a) = stack.status().and_then(|s| entry(&s, victim)) {
            gone_for = gone_for.max(a["last_seen_seconds"].as_f64().unwrap());
        }
        std::thread::sleep(Duration::from_millis(500));
    }
    let cut_off = entry(&stack.status().unwrap(), victim).unwrap();
    docker(&["network", "connect", &network, victim]);
    let back = ingesting_beyond(
        stack,
        &[victim.to_string()],
        &[(u(&cut_off, "incarnation"), u(&cut_off, "stored_through"))],
        Duration::from_secs(60),
    );
    let after = entry(&stack.status().unwrap(), victim).unwrap();
    let own = stack.actor_status(victim);
    eprintln!(
        "partition: {} cut off for {:.1} s; the learner last heard from it {gone_for:.1} s before; stored through {} -> {} (cut off) -> {} (back); ingesting {:.2} s after the reconnect; incarnation {} -> {}; the actor reconnected {} time(s), {} duplicate(s) refused from it",
        actor_id(victim),
        PARTITION.as_secs_f64(),
        u(&before, "stored_through"),
        u(&cut_off, "stored_through"),
        u(&after, "stored_through"),
        back.as_secs_f64(),
        u(&before, "incarnation"),
        u(&after, "incarnation"),
        u(&own, "reconnects"),
        u(&after, "duplicates"),
    );
    assert!(
        gone_for >= GONE,
        "the learner never saw the actor gone: {gone_for}"
    );
    assert_eq!(
        u(&before, "incarnation"),
        u(&after, "incarnation"),
        "the partitioned actor kept its incarnation"
    );
    assert!(u(&own, "reconnects") >= 1, "{own}");
    // Back-off is capped at 5 s: a reconnected actor is back within a couple of its periods.
    assert!(
        back < Duration::from_secs(15),
        "{back:?}\n{}",
        stack.tails()
    );

    // Its accounting: stopped with SIGTERM (it flushes until durable), what it sent against
    // what the learner stored from this incarnation, resends included; then started again.
    docker(&["stop", "--time", "60", victim]);
    let log = container_log(victim);
    let stopped = log_event(&log, "actor stopped")
        .pop()
        .unwrap_or_else(|| panic!("{victim} did not stop cleanly:\n{log}"))["fields"]
        .clone();
    let learner_side = entry(&stack.status().unwrap(), victim).unwrap();
    eprintln!(
        "partition accounting: the actor sent {} transitions, {} acknowledged durable, {} undurable; the learner stored {} from its incarnation {} and refused {} resent message(s) as duplicates",
        u(&stopped, "sent_transitions"),
        u(&stopped, "durable_transitions"),
        u(&stopped, "undurable"),
        u(&learner_side, "transitions"),
        u(&learner_side, "incarnation"),
        u(&learner_side, "duplicates"),
    );
    assert_eq!(u(&stopped, "incarnation"), u(&learner_side, "incarnation"));
    assert_eq!(u(&stopped, "undurable"), 0, "{stopped}");
    assert_eq!(
        u(&stopped, "sent_transitions"),
        u(&stopped, "durable_transitions"),
        "{stopped}"
    );
    assert_eq!(
        u(&stopped, "sent_transitions"),
        u(&learner_side, "transitions"),
        "{stopped} {learner_side}"
    );
    docker(&["start", victim]);
    let restarted = ingesting_beyond(
        stack,
        &[victim.to_string()],
        &[(
            u(&learner_side, "incarnation"),
            u(&learner_side, "stored_through"),
        )],
        Duration::from_secs(60),
    );
    eprintln!(
        "partition: the actor started again, ingesting under a new incarnation {:.1} s later",
        restarted.as_secs_f64()
    );
}

fn scale(stack: &Stack) {
    let learner_log_before = stack.logs("hac-learner").lines().count();
    let mut figures = Vec::new();
    for trainers in [1, 4, 1] {
        let started = Instant::now();
        stack.up(trainers);
        let containers = stack.containers("hac-actor");
        assert_eq!(containers.len(), trainers, "{containers:?}");
        let above = stored(stack, &containers)
            .unwrap_or_else(|| vec![(0, 0); 0])
            .into_iter()
            .chain(std::iter::repeat((0, 0)))
            .take(trainers)
            .collect::<Vec<_>>();
        // The new ones registered and ingesting; the ones kept go on.
        let zero = vec![(0, 0); trainers];
        let above = if above.len() == trainers { above } else { zero };
        let took = ingesting_beyond(stack, &containers, &above, Duration::from_secs(90));
        figures.push(format!(
            "{trainers} trainer(s) ingesting {:.1} s after `up --scale`",
            (started.elapsed()).as_secs_f64().max(took.as_secs_f64())
        ));
    }
    let log = stack.logs("hac-learner");
    let new: Vec<&str> = log.lines().skip(learner_log_before).collect();
    let errors = errors(&new.join("\n")).join("\n");
    eprintln!("scale 1 -> 4 -> 1: {}", figures.join("; "));
    assert!(errors.is_empty(), "errors in the learner's log:\n{errors}");
}

/// The learner's checkpoints written so far (`checkpoint written` events).
fn checkpoints(stack: &Stack) -> Vec<Value> {
    log_event(&stack.logs("hac-learner"), "checkpoint written")
}

fn rolling_restart(stack: &Stack, containers: &[String]) {
    let learner = stack.learner_container();
    let before = stored(stack, containers).unwrap();
    let written = checkpoints(stack).len();
    let stops = |c: &String| log_event(&container_log(c), "actor stopped").len();
    let stops_before: Vec<usize> = containers.iter().map(stops).collect();
    let stopping = Instant::now();
    stack.run(&["stop", "--timeout", "60", "hac-learner"]);
    let stopped = stopping.elapsed();
    // Every actor got the final weights (the run is over for this learner process) and stopped
    // cleanly; Compose starts it again.
    for (container, before) in containers.iter().zip(stops_before) {
        wait_for(
            "the actor stopped on the final weights",
            Duration::from_secs(30),
            || container_log(container),
            || {
                let log = container_log(container);
                let stopped = log_event(&log, "actor stopped");
                (stopped.len() > before
                    && stopped.last().unwrap()["fields"]["run_finished"] == true)
                    .then_some(())
            },
        );
    }
    assert_eq!(
        inspect(&learner, "{{.State.ExitCode}}"),
        "0",
        "{}",
        stack.tails()
    );
    let all = checkpoints(stack);
    assert!(
        all.len() > written,
        "no final checkpoint\n{}",
        stack.tails()
    );
    let last = all.last().unwrap();
    let starting = Instant::now();
    stack.run(&["start", "hac-learner"]);
    // What the resumed learner knows of each actor when it first answers (from its checkpoint);
    // the actors, restarted after the final weights, come back under new incarnations.
    let (resumed, _) = wait_for(
        "the learner answering after its start",
        LEARNER_BACK,
        || stack.tails(),
        || {
            let status = stack.status()?;
            Some(
                containers
                    .iter()
                    .map(|c| {
                        entry(&status, c)
                            .map_or((0, 0), |a| (u(&a, "incarnation"), u(&a, "stored_through")))
                    })
                    .collect::<Vec<_>>(),
            )
        },
    );
    ingesting_beyond(stack, containers, &resumed, LEARNER_BACK);
    let back = starting.elapsed();
    let after = stored(stack, containers).unwrap();
    eprintln!(
        "rolling restart: SIGTERM -> drained and stopped in {:.1} s, final checkpoint {} (weights version {}, {} episodes); started again, every actor ingesting {:.1} s later; (incarnation, stored through) {before:?} -> {after:?}",
        stopped.as_secs_f64(),
        last["fields"]["checkpoint"],
        last["fields"]["weights_version"],
        last["fields"]["episodes"],
        back.as_secs_f64(),
    );
}

fn learner_loss(stack: &Stack, containers: &[String]) {
    let learner = stack.learner_container();
    // A timer checkpoint after the restart, then more in the write-ahead log only.
    std::thread::sleep(Duration::from_secs(7));
    let before_status = stack.status().unwrap();
    let before = stored(stack, containers).unwrap();
    let newest = checkpoints(stack).last().cloned().expect("a checkpoint");
    crash(&learner);
    let killed = Instant::now();
    let (resumed, answers) = wait_for(
        "the learner answering again",
        Duration::from_secs(60),
        || stack.tails(),
        || {
            let s = stack.status()?;
            (s["uptime_seconds"].as_f64()? < killed.elapsed().as_secs_f64()).then_some(s)
        },
    );
    ingesting_beyond(stack, containers, &before, Duration::from_secs(60));
    let back = killed.elapsed();
    let after = stored(stack, containers).unwrap();
    let log = stack.logs("hac-learner");
    let resuming = log_event(&log, "resuming the run");
    eprintln!(
        "learner loss: SIGKILL; restarted by Compose, answering after {:.1} s (weights version {} -> {}, episodes {} -> {}; newest checkpoint {} at version {}); every actor ingesting again {:.1} s after the kill; (incarnation, stored through) {before:?} -> {after:?}",
        answers.as_secs_f64(),
        u(&before_status, "weights_version"),
        u(&resumed, "weights_version"),
        u(&before_status, "episodes"),
        u(&resumed, "episodes"),
        newest["fields"]["checkpoint"],
        newest["fields"]["weights_version"],
        back.as_secs_f64(),
    );
    assert!(
        !resuming.is_empty(),
        "the learner did not resume\n{}",
        stack.tails()
    );
    // It continues the run: versions and counters from the checkpoint, not from zero.
    assert!(
        u(&resumed, "weights_version") >= newest["fields"]["weights_version"].as_u64().unwrap(),
        "{resumed}"
    );
    assert!(
        u(&resumed, "episodes") >= newest["fields"]["episodes"].as_u64().unwrap(),
        "{resumed}"
    );
    assert!(back < LEARNER_BACK, "{back:?}\n{}", stack.tails());
    // What the learner acknowledged was durable: every actor kept its incarnation.
    for ((inc_before, _), (inc_after, _)) in before.iter().zip(&after) {
        assert_eq!(
            inc_before,
            inc_after,
            "an actor was renumbered\n{}",
            stack.tails()
        );
    }
}

/// Stops every actor (SIGTERM: flushed until durable), then the learner; checks what each side
/// counted.
fn accounting(stack: &Stack) {
    let evaluators = stack.containers("hac-evaluator");
    let actors_now: Vec<String> = stack
        .containers("hac-actor")
        .into_iter()
        .chain(evaluators.iter().cloned())
        .collect();
    stack.run(&["stop", "--timeout", "60", "hac-actor", "hac-evaluator"]);
    let status = stack.status().unwrap();
    let mut lines = Vec::new();
    for container in &actors_now {
        let log = container_log(container);
        let stops = log_event(&log, "actor stopped");
        let last = stops
            .last()
            .unwrap_or_else(|| panic!("{container} did not stop cleanly:\n{log}"))["fields"]
            .clone();
        let learner_side = entry(&status, container).unwrap();
        let (sent, durable) = (
            u(&last, "sent_transitions"),
            u(&last, "durable_transitions"),
        );
        lines.push(format!(
            "{}: sent {sent} transitions, acknowledged durable {durable}, undurable {}; learner: {} transitions stored from it, stored through {}, durable through {}, {} duplicate(s) refused",
            actor_id(container),
            u(&last, "undurable"),
            u(&learner_side, "transitions"),
            u(&learner_side, "stored_through"),
            u(&learner_side, "durable_through"),
            u(&learner_side, "duplicates"),
        ));
        assert_eq!(u(&last, "undurable"), 0, "{last}");
        assert_eq!(sent, durable, "{last}");
        assert_eq!(
            u(&learner_side, "stored_through"),
            u(&learner_side, "durable_through"),
            "{learner_side}"
        );
        assert_eq!(
            u(&last, "incarnation"),
            u(&learner_side, "incarnation"),
            "{last} {learner_side}"
        );
        // What this incarnation sent is what the learner stored from it: nothing lost across
        // the learner's restarts, no resend stored twice.
        assert_eq!(
            sent,
            u(&learner_side, "transitions"),
            "{last} {learner_side}"
        );
        // Never renumbered because a restarted learner lacked what it had acknowledged. (An
        // evaluator sends no transitions: the learner's checkpoint and log do not know it, and
        // it is renumbered after a learner's restart with nothing to lose.)
        if !evaluators.contains(container) {
            assert!(
                !log.lines()
                    .any(|l| l.contains("registered again") && l.contains("\"kept\":false")),
                "{container} was renumbered:\n{log}"
            );
        }
    }
    let learner = stack.learner_container();
    stack.run(&["stop", "--timeout", "60", "hac-learner"]);
    assert_eq!(inspect(&learner, "{{.State.ExitCode}}"), "0");
    let summary = learner_summary(&learner, "summary");
    eprintln!(
        "accounting:\n  {}\n  learner (the whole run): messages {}, batches {}, transitions {} (in replay {}), duplicates refused {}, rejected {}",
        lines.join("\n  "),
        common::count(&summary, "messages"),
        common::count(&summary, "batches"),
        common::count(&summary, "transitions"),
        common::count(&summary, "transitions_in_replay"),
        common::count(&summary, "duplicates"),
        common::rejected(&summary),
    );
    // Not `messages = batches + episodes + duplicates + rejected`: `rejected` also counts what
    // is not an ingest message (registrations refused while the learner finishes, evaluations of
    // a killed learner's weights, weights watches of unknown actors).
    assert_eq!(
        common::count(&summary, "transitions"),
        u(&status, "transitions"),
        "{summary}"
    );
    let errors = errors(&stack.logs("hac-learner"))
        .into_iter()
        .map(str::to_string)
        .collect::<Vec<_>>();
    assert!(errors.is_empty(), "{errors:?}");
}

fn faults(image: &Image) {
    let stack = Stack::new("faults", &["compose.yaml"], image, Some(FAULT_RUN));
    let containers = bring_up(&stack, 2);
    let status = stack.status().unwrap();
    let metrics = metrics(stack.metrics);
    assert!(
        metrics.starts_with("HTTP/1.") && metrics.contains(" 200 ") && metrics.contains("hac_"),
        "{metrics}"
    );
    eprintln!(
        "status from the host: {} actors ({}); /metrics: {} lines",
        actors(&status).len(),
        actors(&status)
            .iter()
            .map(|a| format!("{} {}", a["actor_id"], a["role"]))
            .collect::<Vec<_>>()
            .join(", "),
        metrics.lines().count()
    );
    drop(containers);
    scale(&stack);
    stack.up(2);
    let containers = stack.containers("hac-actor");
    assert_eq!(containers.len(), 2, "{containers:?}");
    ingesting_beyond(
        &stack,
        &containers,
        &[(0, 0), (0, 0)],
        Duration::from_secs(90),
    );
    node_loss(&stack, &containers[0]);
    partition(&stack, &containers[1]);
    rolling_restart(&stack, &containers);
    learner_loss(&stack, &containers);
    accounting(&stack);
}

fn shared_memory(image: &Image) {
    let stack = Stack::new(
        "shm",
        &["compose.yaml", "compose.shm.yaml"],
        image,
        Some(FAULT_RUN),
    );
    let started = Instant::now();
    // Two trainers: the learner's one subscriber serves both (it reads in rounds of one
    // message per actor; reading in the subscriber's order once left the second at 0).
    stack.up(2);
    let trainers = stack.containers("hac-actor");
    assert_eq!(trainers.len(), 2, "{trainers:?}");
    // The actors have the learner's host name: their ids are `hac-shm-host-<pid>`.
    let (ingesting, _) = wait_for(
        "both trainers ingesting over shared memory",
        Duration::from_secs(120),
        || stack.tails(),
        || {
            let over_shm: Vec<_> = actors(&stack.status()?)
                .into_iter()
                .filter(|a| {
                    a["role"] == "trainer" && a["transport"] == "shm" && u(a, "stored_through") > 0
                })
                .collect();
            (over_shm.len() == 2).then_some(over_shm)
        },
    );
    for trainer in &trainers {
        let log = container_log(trainer);
        assert!(log.contains(common::USING_SHM), "{log}");
    }
    for trainer in &ingesting {
        eprintln!(
            "shared memory: trainer {} ingesting over shm {:.1} s after `up` (stored through {})",
            trainer["actor_id"],
            started.elapsed().as_secs_f64(),
            u(trainer, "stored_through")
        );
    }
}

fn eight_trainers(image: &Image) {
    // Episode turns (one episode in flight): the embedded run's schedule with any number of
    // trainers, each episode drawing from the seed's streams of its index, so the trained
    // networks are those of one trainer alone with the same seed
    // (crates/serve/tests/integration/turns.rs), not a draw that depends on which container played which episode. Free-running trainers (deploy/hac.toml's `episodes_in_flight = 0`) reached 90 %
    // here too when the machine was otherwise idle, but not while a build took its 2 cores: the
    // learner fell behind and the trainers played on stale weights (docs/OPERATIONS.md).
    let stack = Stack::new("eight", &["compose.yaml"], image, Some(EIGHT_RUN));
    let started = Instant::now();
    stack.up(8);
    let learner = stack.learner_container();
    // deploy/hac.toml with the budget above: pendulum, 2 levels, stop at 90 %. The learner
    // exits 0 once the run is over.
    let ((), took) = wait_for(
        "the run finished",
        Duration::from_secs(1800),
        || stack.tails(),
        || (inspect(&learner, "{{.State.Status}}") == "exited").then_some(()),
    );
    assert_eq!(
        inspect(&learner, "{{.State.ExitCode}}"),
        "0",
        "{}",
        stack.tails()
    );
    let summary = learner_summary(&learner, "eight-summary");
    eprintln!(
        "8 trainers: the run finished {:.1} s after `up` (the learner's wall time {:.1} s); episodes to 90 %: {}, best success {}, final success {}, {} episodes ingested",
        took.as_secs_f64().max(started.elapsed().as_secs_f64()),
        summary["wall_time_s"].as_f64().unwrap(),
        summary["episodes_to_90"],
        summary["best_success"],
        summary["final_success"],
        summary["episodes_ingested"],
    );
    // The run stops at the first test round at 90 % or above (the final one, played after the
    // stop with the final weights, is reported beside it).
    assert!(summary["episodes_to_90"].is_u64(), "{summary}");
    assert!(
        summary["best_success"].as_f64().unwrap() >= 0.9,
        "{summary}"
    );
}

#[test]
fn the_compose_cluster_survives_node_loss_partitions_and_learner_restarts() {
    if !common::tools_opted_in(
        "the_compose_cluster_survives_node_loss_partitions_and_learner_restarts",
        "docker, docker compose v2 and debootstrap",
    ) {
        return;
    }
    let started = Instant::now();
    let image = build_image();
    faults(&image);
    shared_memory(&image);
    eight_trainers(&image);
    eprintln!(
        "containers: {:.0} s in all",
        started.elapsed().as_secs_f64()
    );
}
