//! The config file shared by both daemons: every bad key or value is refused with the key named
//! before anything is bound; the precedence flag > `HAC_*` > file > default; `--print-config`
//! output feeds back; the example deployment file is valid for both daemons; and the key lists
//! and docs/CONFIG.md stay in step with the daemons' flags (`HAC_BLESS=1` rewrites them).

use std::path::{Path, PathBuf};
use std::process::Output;

use crate::common::{hac_command, text};

fn root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../..")
}

fn hac(args: &[&str], env: &[(&str, &str)]) -> Output {
    let mut cmd = hac_command(args, &[]);
    // Nothing from the caller's environment may leak into the cases.
    for (key, _) in std::env::vars() {
        if key.starts_with("HAC_") {
            cmd.env_remove(key);
        }
    }
    cmd.envs(env.iter().copied())
        .output()
        .expect("the hac binary runs")
}

struct Scratch(PathBuf);

impl Scratch {
    fn new(name: &str) -> Self {
        Self(crate::common::scratch("hac-config-test", name))
    }

    fn file(&self, name: &str, text: &str) -> String {
        let path = self.0.join(name);
        std::fs::write(&path, text).unwrap();
        path.to_str().unwrap().to_string()
    }
}

impl Drop for Scratch {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.0);
    }
}

/// A bad configuration: the file, extra variables, text the error must contain, and the
/// daemons that must refuse it.
struct Case {
    file: &'static str,
    vars: &'static [(&'static str, &'static str)],
    expected: &'static str,
    daemons: &'static [&'static str],
}

impl Case {
    /// A bad file, refused by both daemons.
    fn file(file: &'static str, expected: &'static str) -> Self {
        Self {
            file,
            vars: &[],
            expected,
            daemons: &["learner", "actor"],
        }
    }
}

#[test]
fn every_wrong_key_or_value_stops_both_daemons_before_they_bind() {
    let scratch = Scratch::new("bad");
    let out = scratch.0.join("out");
    let cases = [
        Case::file("levls = 2\n", "levls"),
        Case::file(
            "[learner]\nlistne = \"127.0.0.1:0\"\n",
            "unknown key `[learner] listne`",
        ),
        Case::file("[actor]\nwindwo = 3\n", "unknown key `[actor] windwo`"),
        Case::file(
            "[learner]\nmax_message_bytes = \"big\"\n",
            "invalid value for `[learner] max_message_bytes`",
        ),
        Case::file(
            "[actor]\nwindow = 0\n",
            "invalid value for `[actor] window`",
        ),
        // Run values are checked with the run (naming the key, not the file).
        Case::file("levels = 20\n", "invalid value for `levels`"),
        Case::file("[agent]\ngamma = 2.0\n", "gamma"),
        Case::file("[learner]\nseed = 3\n", "`seed` is a run key"),
        Case::file(
            "[learner]\ncheckpoint_every = \"often\"\n",
            "`[learner] checkpoint_every`",
        ),
        Case {
            file: "",
            vars: &[("HAC_MAX_MESSAGE_BYTES", "12")],
            expected: "HAC_MAX_MESSAGE_BYTES",
            daemons: &["learner"],
        },
        Case {
            file: "",
            vars: &[("HAC_WINDOW", "many")],
            expected: "HAC_WINDOW",
            daemons: &["actor"],
        },
    ];
    for (
        i,
        Case {
            file,
            vars,
            expected,
            daemons,
        },
    ) in cases.iter().enumerate()
    {
        let path = scratch.file(&format!("bad{i}.toml"), file);
        for daemon in *daemons {
            let mut args = vec![*daemon, "--config", &path];
            if *daemon == "learner" {
                args.extend(["--listen", "127.0.0.1:0", "--out", out.to_str().unwrap()]);
            } else {
                // Would be refused at once if it got as far as connecting.
                args.extend(["--learner", "http://127.0.0.1:9", "--give-up-after", "1"]);
            }
            let o = hac(&args, vars);
            let (stdout, stderr) = (text(&o.stdout), text(&o.stderr));
            assert!(!o.status.success(), "{daemon} accepted {file:?} {vars:?}");
            assert!(
                stderr.contains(expected),
                "{daemon} on {file:?} {vars:?}: expected {expected:?} in\n{stderr}"
            );
            assert!(
                !stdout.contains("listening on") && !stderr.contains("listening"),
                "{daemon} bound a port first: {stdout}{stderr}"
            );
            if file.contains('[') && !file.contains("[agent]") || file.contains("levls") {
                assert!(
                    stderr.contains(&path),
                    "{daemon}: the file is named: {stderr}"
                );
            }
        }
    }
    assert!(!out.exists(), "nothing was written");
}

#[test]
fn flags_beat_variables_beat_the_file_beats_the_defaults() {
    let scratch = Scratch::new("precedence");
    let file = scratch.file(
        "hac.toml",
        "env = \"mountain-car\"\n[learner]\ngrace_period = 7\ndrain_timeout = 7\nkeep_checkpoints = 7\n[actor]\nwindow = 7\n",
    );
    let o = hac(
        &[
            "learner",
            "--config",
            &file,
            "--print-config",
            "--drain-timeout",
            "9",
        ],
        &[("HAC_GRACE_PERIOD", "8"), ("HAC_DRAIN_TIMEOUT", "8")],
    );
    assert!(o.status.success(), "{}", text(&o.stderr));
    let printed = text(&o.stdout);
    for line in [
        "env = \"mountain-car\"",
        "[learner]",
        "grace_period = 8",
        "drain_timeout = 9",
        "keep_checkpoints = 7",
        "checkpoint_every = 300",
        "listen = \"127.0.0.1:50051\"",
    ] {
        assert!(printed.lines().any(|l| l == line), "{line} in\n{printed}");
    }
    // The printed configuration is a config file that resolves to itself.
    let again = scratch.file("printed.toml", &printed);
    let o = hac(&["learner", "--config", &again, "--print-config"], &[]);
    assert!(o.status.success(), "{}", text(&o.stderr));
    assert_eq!(text(&o.stdout), printed);

    let o = hac(&["actor", "--config", &file, "--print-config"], &[]);
    assert!(o.status.success(), "{}", text(&o.stderr));
    let printed = text(&o.stdout);
    assert!(
        printed.contains("[actor]\n") && printed.contains("\nwindow = 7\n"),
        "{printed}"
    );

    // `hac train` takes the same file: it checks the daemons' tables and ignores them.
    let o = hac(&["train", "--config", &file, "--print-config"], &[]);
    assert!(o.status.success(), "{}", text(&o.stderr));
    assert!(text(&o.stdout).contains("env = \"mountain-car\""));
    let typo = scratch.file("typo.toml", "[actor]\nwindwo = 3\n");
    let o = hac(&["train", "--config", &typo, "--print-config"], &[]);
    assert!(!o.status.success());
    assert!(
        text(&o.stderr).contains("[actor] windwo"),
        "{}",
        text(&o.stderr)
    );
}

#[test]
fn the_deployment_config_is_valid_for_both_daemons() {
    let file = root().join("deploy/hac.toml");
    let file = file.to_str().unwrap();
    for daemon in ["learner", "actor"] {
        let o = hac(&[daemon, "--config", file, "--print-config"], &[]);
        assert!(
            o.status.success(),
            "{daemon} refuses deploy/hac.toml: {}",
            text(&o.stderr)
        );
        assert!(text(&o.stdout).contains(&format!("[{daemon}]")));
    }
    let o = hac(&["learner", "--config", file, "--print-config"], &[]);
    let printed = text(&o.stdout);
    assert!(printed.contains("out = \"/var/lib/hac/run\""), "{printed}");
    assert!(printed.contains("resume = true"), "{printed}");
}

/// Compares `path` with `expected`, or rewrites it when `HAC_BLESS` is set.
fn in_step(path: &Path, expected: &str) {
    if std::env::var_os("HAC_BLESS").is_some() {
        std::fs::write(path, expected).unwrap();
        return;
    }
    let found = std::fs::read_to_string(path).unwrap_or_default();
    assert!(
        found == expected,
        "{} is out of date with the daemons' flags; run `HAC_BLESS=1 cargo test -p hac-cli \
         --test integration config::` and review the diff",
        path.display()
    );
}

#[test]
fn key_lists_and_docs_are_in_step_with_the_flags() {
    let learner = hac_learner_service::config_section();
    let actor = hac_actor_service::config_section();
    let list = |keys: Vec<String>| {
        keys.iter()
            .map(|k| format!("    \"{k}\",\n"))
            .collect::<String>()
    };
    let keys = format!(
        "//! The keys of the daemons' tables, generated from their clap definitions; do not edit. The\n\
         //! `hac` binary links both daemons and checks both tables against their definitions; a daemon's\n\
         //! own binary checks the other daemon's table against this list. `cargo test -p hac-cli --test\n\
         //! integration config::` fails while the list is out of date; `HAC_BLESS=1` on that command rewrites it.\n\
         \n\
         /// `[learner]`.\n\
         pub const LEARNER: &[&str] = &[\n{}];\n\
         \n\
         /// `[actor]`.\n\
         pub const ACTOR: &[&str] = &[\n{}];\n",
        list(learner.keys()),
        list(actor.keys())
    );
    in_step(&root().join("crates/run/src/daemon/keys.rs"), &keys);

    let docs_path = root().join("docs/CONFIG.md");
    let mut docs = std::fs::read_to_string(&docs_path).unwrap();
    for section in [&learner, &actor] {
        let begin = format!("<!-- BEGIN GENERATED [{}] -->\n", section.name());
        let end = format!("<!-- END GENERATED [{}] -->", section.name());
        let (Some(start), Some(stop)) = (docs.find(&begin), docs.find(&end)) else {
            panic!("docs/CONFIG.md lacks the markers {begin:?} and {end:?}");
        };
        docs.replace_range(start + begin.len()..stop, &section.markdown());
    }
    in_step(&docs_path, &docs);
}

/// `hac train` and `hac experiment` take the learner's thread budget; a bad one is refused by
/// name before any run directory is made.
#[test]
fn train_and_experiment_refuse_a_bad_learner_thread_budget() {
    let scratch = Scratch::new("learner-threads");
    let out = scratch.0.join("run");
    let out = out.to_str().unwrap();
    // Arguments, variables, the error expected.
    type Refusal<'a> = (&'a [&'a str], &'a [(&'a str, &'a str)], &'a str);
    let cases: [Refusal; 3] = [
        (
            &["train", "--learner-threads", "0", "--out", out],
            &[],
            "invalid value for `learner_threads`: must be 1 to 1024, got 0",
        ),
        (
            &["train", "--out", out],
            &[("HAC_LEARNER_THREADS", "1025")],
            "invalid value for `learner_threads`: must be 1 to 1024, got 1025",
        ),
        (
            &[
                "experiment",
                "--env",
                "pendulum",
                "--learner-threads",
                "0",
                "--out",
                out,
            ],
            &[],
            "invalid value for `--learner-threads`: must be 1 to 1024, got 0",
        ),
    ];
    for (args, env, expected) in cases {
        let output = hac(args, env);
        let stderr = text(&output.stderr);
        assert!(!output.status.success(), "{args:?} {env:?} succeeded");
        assert!(stderr.contains(expected), "{args:?} {env:?}: {stderr}");
        assert!(!Path::new(out).exists(), "{args:?} {env:?} made {out}");
    }
}
