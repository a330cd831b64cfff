//! What the daemons define (their clap arguments and `hac learner|actor --help`), and a daemon
//! process as a deployment file describes it (argv, environment, config file), with the daemons'
//! precedence: flag, then `HAC_*` variable, then the file.

use std::collections::{BTreeMap, BTreeSet};
use std::path::Path;
use std::process::Command;
use std::sync::OnceLock;

use clap::Args as _;

use super::HAC;

#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord)]
pub enum Daemon {
    Learner,
    Actor,
}

impl Daemon {
    pub fn subcommand(self) -> &'static str {
        match self {
            Daemon::Learner => "learner",
            Daemon::Actor => "actor",
        }
    }

    pub fn binary(self) -> &'static str {
        match self {
            Daemon::Learner => "hac-learner",
            Daemon::Actor => "hac-actor",
        }
    }

    /// Which daemon a container runs: `hac-learner ...`, `hac-actor ...` or `hac learner|actor`.
    pub fn of_command(argv: &[String]) -> Option<(Daemon, Vec<String>)> {
        let program = Path::new(argv.first()?).file_name()?.to_str()?;
        let (daemon, rest) = match program {
            "hac-learner" => (Daemon::Learner, &argv[1..]),
            "hac-actor" => (Daemon::Actor, &argv[1..]),
            "hac" => match argv.get(1).map(String::as_str) {
                Some("learner") => (Daemon::Learner, &argv[2..]),
                Some("actor") => (Daemon::Actor, &argv[2..]),
                _ => return None,
            },
            _ => return None,
        };
        Some((daemon, rest.to_vec()))
    }

    /// The shared clap definition (`hac-learner` and `hac learner` both flatten it).
    pub fn command(self) -> clap::Command {
        let command = clap::Command::new(self.binary()).no_binary_name(true);
        match self {
            Daemon::Learner => hac_learner_service::LearnerArgs::augment_args(command),
            Daemon::Actor => hac_actor_service::ActorArgs::augment_args(command),
        }
    }
}

/// One option as `hac <daemon> --help` shows it.
#[derive(Debug, Clone, Default)]
pub struct HelpOption {
    long: String,
    env: Option<String>,
    possible_values: Vec<String>,
}

/// The options of `hac learner --help` or `hac actor --help` (the real binary: it includes the
/// flags the binary adds around the shared definition, such as `--log-format`).
pub fn help_options(daemon: Daemon) -> &'static [HelpOption] {
    static HELP: OnceLock<BTreeMap<Daemon, Vec<HelpOption>>> = OnceLock::new();
    &HELP.get_or_init(|| {
        [Daemon::Learner, Daemon::Actor]
            .into_iter()
            .map(|d| (d, parse_help(d)))
            .collect()
    })[&daemon]
}

pub fn parse_help(daemon: Daemon) -> Vec<HelpOption> {
    let output = Command::new(HAC)
        .args([daemon.subcommand(), "--help"])
        .output()
        .unwrap();
    assert!(
        output.status.success(),
        "hac {} --help",
        daemon.subcommand()
    );
    let text = String::from_utf8(output.stdout).unwrap();
    let mut options: Vec<HelpOption> = Vec::new();
    for line in text.lines() {
        let indent = line.len() - line.trim_start().len();
        let trimmed = line.trim();
        if indent <= 6 && trimmed.starts_with('-') {
            let long = trimmed
                .split([' ', ','])
                .find_map(|word| word.strip_prefix("--"))
                .unwrap_or_default();
            options.push(HelpOption {
                long: long.to_string(),
                ..HelpOption::default()
            });
        } else if let Some(option) = options.last_mut() {
            if let Some(env) = trimmed
                .strip_prefix("[env: ")
                .and_then(|rest| rest.split('=').next())
            {
                option.env = Some(env.to_string());
            } else if let Some(value) = trimmed
                .strip_prefix("- ")
                .and_then(|rest| rest.split(':').next())
            {
                option.possible_values.push(value.to_string());
            }
        }
    }
    options
}

/// Does `daemon` accept `--<long> [value]`? Checked by the real clap definition where the flag
/// is defined there, and by the binary's help otherwise.
pub fn check_flag(daemon: Daemon, long: &str, value: Option<&str>) -> Result<(), String> {
    let command = daemon.command();
    let takes_value = command
        .get_arguments()
        .find(|a| a.get_long() == Some(long))
        .map(|arg| arg.get_action().takes_values());
    if let Some(takes_value) = takes_value {
        let mut argv = vec![format!("--{long}")];
        match (takes_value, value) {
            (true, Some(value)) => argv.push(value.to_string()),
            (true, None) => return Err(format!("--{long} needs a value")),
            (false, Some(v)) if !is_boolish(v) => {
                return Err(format!("--{long} is a switch, `{v}` is not true or false"));
            }
            (false, _) => {}
        }
        return command
            .try_get_matches_from(&argv)
            .map(|_| ())
            .map_err(|e| format!("`{}`: {}", argv.join(" "), e.kind()));
    }
    let Some(option) = help_options(daemon).iter().find(|o| o.long == long) else {
        return Err(format!("`{}` has no flag --{long}", daemon.binary()));
    };
    match value {
        Some(v)
            if !option.possible_values.is_empty()
                && !option.possible_values.iter().any(|p| p == v) =>
        {
            Err(format!(
                "--{long} {v}: not one of {:?}",
                option.possible_values
            ))
        }
        _ => Ok(()),
    }
}

pub fn is_boolish(value: &str) -> bool {
    matches!(
        value.to_ascii_lowercase().as_str(),
        "true" | "false" | "yes" | "no" | "on" | "off" | "1" | "0"
    )
}

/// The long flag a `HAC_*` variable stands for, by the binary's own definitions.
pub fn flag_of_env(daemon: Daemon, name: &str) -> Option<String> {
    daemon
        .command()
        .get_arguments()
        .find(|a| a.get_env().is_some_and(|e| e == name))
        .and_then(|a| a.get_long().map(str::to_string))
        .or_else(|| {
            help_options(daemon)
                .iter()
                .find(|o| o.env.as_deref() == Some(name))
                .map(|o| o.long.clone())
        })
}

/// The variable the binary reads for a flag (or, for a flag it does not have yet, the
/// `HAC_<KEY>` the contract names, so that resolution still works and the missing flag is
/// reported once, where it is used).
pub fn env_of_flag(daemon: Daemon, long: &str) -> String {
    daemon
        .command()
        .get_arguments()
        .find(|a| a.get_long() == Some(long))
        .and_then(|a| a.get_env().map(|e| e.to_string_lossy().into_owned()))
        .unwrap_or_else(|| format!("HAC_{}", long.replace('-', "_").to_uppercase()))
}

pub fn check_env(daemon: Daemon, name: &str, value: &str) -> Result<(), String> {
    if name == "HAC_TOKEN" {
        return Err(
            "the token itself belongs in a file (HAC_TOKEN_FILE), not in the manifest".into(),
        );
    }
    let Some(long) = flag_of_env(daemon, name) else {
        return Err(format!("`{}` reads no variable {name}", daemon.binary()));
    };
    check_flag(daemon, &long, Some(value)).map_err(|e| format!("{name}={value}: {e}"))
}

/// The `[learner]` / `[actor]` table's keys: the daemon's long flags with `-` as `_`.
pub fn check_config_table(daemon: Daemon, config: &toml::Table) -> Vec<String> {
    let Some(table) = config.get(daemon.subcommand()) else {
        return Vec::new();
    };
    let Some(table) = table.as_table() else {
        return vec![format!("[{}] is not a table", daemon.subcommand())];
    };
    let mut problems = Vec::new();
    for (key, value) in table {
        let long = key.replace('_', "-");
        let values: Vec<Option<String>> = match value {
            toml::Value::String(s) => vec![Some(s.clone())],
            toml::Value::Boolean(b) => vec![Some(b.to_string())],
            toml::Value::Array(items) => items.iter().map(|v| Some(toml_scalar(v))).collect(),
            other => vec![Some(toml_scalar(other))],
        };
        for value in values {
            if let Err(e) = check_flag(daemon, &long, value.as_deref()) {
                problems.push(format!("config key [{}] {key}: {e}", daemon.subcommand()));
            }
        }
    }
    problems
}

pub fn toml_scalar(value: &toml::Value) -> String {
    match value {
        toml::Value::String(s) => s.clone(),
        other => other.to_string(),
    }
}

/// The config file through the real learner: `hac learner --print-config` resolves the whole
/// file (the run keys, and rejects unknown keys in any table).
pub fn check_config_with_learner(path: &Path) -> Vec<String> {
    let output = Command::new(HAC)
        .args(["learner", "--print-config"])
        .env("HAC_CONFIG", path)
        .output()
        .unwrap();
    if output.status.success() {
        Vec::new()
    } else {
        vec![format!(
            "`hac learner --print-config` refuses {}: {}",
            path.display(),
            String::from_utf8_lossy(&output.stderr).trim()
        )]
    }
}

/// Service names each daemon serves health for: "" (the whole server) and its own service, which
/// must exist in the wire contract.
pub fn health_services(daemon: Daemon) -> [&'static str; 2] {
    match daemon {
        Daemon::Learner => ["", "hac.v1.Learner"],
        Daemon::Actor => ["", "hac.v1.Status"],
    }
}

pub fn proto_services() -> BTreeSet<String> {
    use prost::Message as _;
    let set = prost_types::FileDescriptorSet::decode(hac_proto::FILE_DESCRIPTOR_SET).unwrap();
    set.file
        .iter()
        .flat_map(|f| {
            f.service
                .iter()
                .map(move |s| format!("{}.{}", f.package(), s.name()))
        })
        .collect()
}

// ---------------------------------------------------------------------------------------------
// A process as a deployment file describes it

/// One daemon process of a manifest: argv after the program, environment, the config file.
#[derive(Debug)]
pub struct Process {
    pub place: String,
    pub daemon: Daemon,
    pub args: Vec<String>,
    pub env: BTreeMap<String, String>,
    pub config: toml::Table,
}

impl Process {
    /// A setting with the daemons' precedence: flag, then `HAC_*` variable, then the file.
    pub fn setting(&self, key: &str) -> Option<String> {
        let long = format!("--{}", key.replace('_', "-"));
        for (i, arg) in self.args.iter().enumerate() {
            if *arg == long {
                return self.args.get(i + 1).cloned();
            }
            if let Some(value) = arg.strip_prefix(&format!("{long}=")) {
                return Some(value.to_string());
            }
        }
        let env = env_of_flag(self.daemon, &key.replace('_', "-"));
        if let Some(value) = self.env.get(&env) {
            return Some(value.clone());
        }
        self.config
            .get(self.daemon.subcommand())
            .and_then(|t| t.get(key))
            .map(toml_scalar)
    }

    pub fn is_true(&self, key: &str) -> bool {
        self.setting(key)
            .is_some_and(|v| matches!(v.to_ascii_lowercase().as_str(), "true" | "yes" | "on" | "1"))
    }

    /// Flags and variables: each must exist with an accepted value.
    pub fn check_definitions(&self) -> Vec<String> {
        let mut problems = Vec::new();
        let mut i = 0;
        while i < self.args.len() {
            let arg = &self.args[i];
            let Some(flag) = arg.strip_prefix("--") else {
                problems.push(format!("{}: unexpected argument `{arg}`", self.place));
                i += 1;
                continue;
            };
            let (long, value) = match flag.split_once('=') {
                Some((long, value)) => (long, Some(value.to_string())),
                None => {
                    let takes_value = self
                        .daemon
                        .command()
                        .get_arguments()
                        .find(|a| a.get_long() == Some(flag))
                        .is_some_and(|a| a.get_action().takes_values());
                    if takes_value {
                        i += 1;
                        (flag, self.args.get(i).cloned())
                    } else {
                        (flag, None)
                    }
                }
            };
            if let Err(e) = check_flag(self.daemon, long, value.as_deref()) {
                problems.push(format!("{}: {e}", self.place));
            }
            i += 1;
        }
        for (name, value) in &self.env {
            if let Err(e) = check_env(self.daemon, name, value) {
                problems.push(format!("{}: {e}", self.place));
            }
        }
        problems
    }

    pub fn port(&self, key: &str) -> Option<u16> {
        self.setting(key).and_then(|addr| port_of(&addr))
    }
}

/// The port of `host:port` or `scheme://host:port[/...]`.
pub fn port_of(address: &str) -> Option<u16> {
    let rest = address.split_once("://").map_or(address, |(_, r)| r);
    let authority = rest.split('/').next()?;
    authority.rsplit_once(':')?.1.parse().ok()
}

pub fn host_of(url: &str) -> Option<&str> {
    let rest = url.split_once("://")?.1;
    Some(rest.split('/').next()?.rsplit_once(':')?.0)
}
