//! The daemons' tables of the config file, `[learner]` and `[actor]`, derived from the daemons'
//! clap definitions instead of being listed by hand.
//!
//! Every long flag of a daemon is a key of its table, named as the flag with `-` replaced by
//! `_` (`--max-message-bytes` is `[learner] max_message_bytes`), and an environment variable,
//! `HAC_<KEY>` unless the flag names its own. Exceptions: the run keys ([`RUN_KEYS`]), which
//! the file sets at its top level, and `--config`, `--print-config` and `--set`, which belong to
//! the command line. A file value applies only where neither the command line nor the
//! environment gave one (flag > `HAC_*` > file > default), and it goes through the flag's own
//! parser, so the file accepts exactly what the flag accepts.
//!
//! [`parse`] replaces `Parser::parse` in the daemons' `main`: it reads the command line, and if
//! a daemon runs with `--config`, checks the whole file (the top level, the daemon's own table,
//! and the other daemon's table against its definition, or against [`keys`] in a binary that does
//! not link it), then parses again with the file's values. Every error names the key and the
//! file, and comes before anything is bound or started.

use std::ffi::OsString;
use std::path::{Path, PathBuf};

use anyhow::{Context, Result, anyhow, bail};
use clap::error::ErrorKind;
use clap::parser::ValueSource;
use clap::{Arg, ArgAction, ArgMatches, Command, Parser};

pub mod keys;

/// Daemon flags whose file keys live at the top level of the file (they define the run).
pub const RUN_KEYS: [&str; 7] = [
    "env",
    "levels",
    "seed",
    "episodes",
    "stop_at",
    "replay_shards",
    "max_actions",
];

/// Flags that have no key: the file itself, printing it, and agent overrides (the file has
/// `[agent]` for those).
const COMMAND_LINE_ONLY: [&str; 3] = ["config", "print_config", "set"];

/// The flags every daemon has for its config file.
#[derive(Debug, Clone, Default, clap::Args)]
pub struct ConfigArgs {
    /// TOML config file: run keys at the top level (with [agent] and [tabular]), and the
    /// daemons' [learner] and [actor] tables, whose keys are their flags (docs/CONFIG.md).
    #[arg(
        long = "config",
        id = "config",
        env = "HAC_CONFIG",
        value_name = "PATH"
    )]
    pub path: Option<PathBuf>,
    /// Print the resolved configuration as TOML (it can be fed back with --config) and exit.
    #[arg(long = "print-config", id = "print_config")]
    pub print: bool,
    /// This daemon's table as resolved, for `--print-config` ([`parse`] fills it in).
    #[arg(skip)]
    pub resolved: Option<ResolvedSection>,
}

/// One daemon's table of the config file and what it may hold.
#[derive(Debug, Clone)]
pub struct Section {
    name: &'static str,
    schema: Schema,
}

#[derive(Debug, Clone)]
enum Schema {
    /// The daemon's clap definition: keys and values are checked.
    Flags(Box<Command>),
    /// Only the key names (a daemon whose definition this binary does not link).
    Keys(&'static [&'static str]),
}

impl Section {
    /// The table `[name]` of a daemon whose flags are `args` (its `Args` alone, e.g.
    /// `LearnerArgs::augment_args(Command::new("learner"))`).
    pub fn of_flags(name: &'static str, args: Command) -> Self {
        Self {
            name,
            schema: Schema::Flags(Box::new(with_env_vars(args))),
        }
    }

    /// The table `[name]` known only by its keys (see [`keys`]).
    pub fn of_keys(name: &'static str, keys: &'static [&'static str]) -> Self {
        Self {
            name,
            schema: Schema::Keys(keys),
        }
    }

    pub fn name(&self) -> &'static str {
        self.name
    }

    /// The keys of the table, in the definition's order.
    pub fn keys(&self) -> Vec<String> {
        match &self.schema {
            Schema::Flags(cmd) => cmd.get_arguments().filter_map(key_of).collect(),
            Schema::Keys(keys) => keys.iter().map(|k| k.to_string()).collect(),
        }
    }

    /// The daemon's flags, with the `HAC_*` variables added (for documentation).
    pub fn command(&self) -> Option<&Command> {
        match &self.schema {
            Schema::Flags(cmd) => Some(cmd),
            Schema::Keys(_) => None,
        }
    }

    fn arg(&self, key: &str) -> Option<&Arg> {
        self.command()?
            .get_arguments()
            .find(|a| key_of(a).as_deref() == Some(key))
    }

    /// A markdown table of every key: flag, variable, default, meaning (docs/CONFIG.md).
    pub fn markdown(&self) -> String {
        let mut text = String::from(
            "| key | flag / variable | default | meaning |\n| --- | --- | --- | --- |\n",
        );
        let Some(cmd) = self.command() else {
            return text;
        };
        for arg in cmd.get_arguments() {
            let Some(key) = key_of(arg) else { continue };
            let help = arg
                .get_long_help()
                .or(arg.get_help())
                .map(|h| h.to_string())
                .unwrap_or_default();
            let help = help.split_whitespace().collect::<Vec<_>>().join(" ");
            let default_note = default_note(&help);
            let meaning = match help.rsplit_once(" [default: ") {
                Some((meaning, _)) if default_note.is_some() => meaning.to_string(),
                _ => help.clone(),
            };
            let default = if !arg.get_action().takes_values() {
                "false".to_string()
            } else if !arg.get_default_values().is_empty() {
                let values: Vec<String> = arg
                    .get_default_values()
                    .iter()
                    .map(|v| format!("`{}`", v.to_string_lossy()))
                    .collect();
                values.join(", ")
            } else {
                default_note.unwrap_or_else(|| "not set".into())
            };
            let env = arg
                .get_env()
                .map(|e| format!(" / `{}`", e.to_string_lossy()))
                .unwrap_or_default();
            let long = arg.get_long().unwrap_or_default();
            text += &format!(
                "| `{key}` | `--{long}`{env} | {} | {} |\n",
                escape(&default),
                escape(&meaning)
            );
        }
        text
    }
}

/// Text for a markdown table cell: `|` and `<` (an HTML tag to markdown) escaped, except inside
/// code spans.
fn escape(text: &str) -> String {
    let mut out = String::with_capacity(text.len());
    let mut code = false;
    for c in text.chars() {
        match c {
            '`' => code = !code,
            '|' => out.push('\\'),
            '<' if !code => out.push('\\'),
            _ => {}
        }
        out.push(c);
    }
    out
}

/// The file key of a flag, if it has one (see the module docs).
fn key_of(arg: &Arg) -> Option<String> {
    if !matches!(
        arg.get_action(),
        ArgAction::Set | ArgAction::Append | ArgAction::SetTrue | ArgAction::SetFalse
    ) {
        return None;
    }
    let key = arg.get_long()?.replace('-', "_");
    let excluded = RUN_KEYS.contains(&key.as_str()) || COMMAND_LINE_ONLY.contains(&key.as_str());
    (!excluded).then_some(key)
}

/// The `X` of a help text ending in `[default: X]` (or `[default: X].`).
fn default_note(help: &str) -> Option<String> {
    let (_, note) = help.rsplit_once("[default: ")?;
    let note = note.trim_end().trim_end_matches('.').strip_suffix(']')?;
    Some(note.split_whitespace().collect::<Vec<_>>().join(" "))
}

/// Gives every key's flag a `HAC_<KEY>` variable, unless it names its own.
fn with_env_vars(cmd: Command) -> Command {
    cmd.mut_args(|arg| match key_of(&arg) {
        Some(key) if arg.get_env().is_none() => arg.env(format!("HAC_{}", key.to_uppercase())),
        _ => arg,
    })
}

/// A config file, parsed.
#[derive(Debug, Clone)]
pub struct ConfigFile {
    path: PathBuf,
    table: toml::Table,
}

impl ConfigFile {
    pub fn load(path: &Path) -> Result<Self> {
        let text = std::fs::read_to_string(path)
            .with_context(|| format!("reading config file {}", path.display()))?;
        let table: toml::Table = text
            .parse()
            .with_context(|| format!("in config file {}", path.display()))?;
        Ok(Self {
            path: path.to_path_buf(),
            table,
        })
    }

    /// Checks the whole file: the top level (run keys, `[agent]`, `[tabular]` and the daemons'
    /// tables, nothing else) and each of `sections` present, key by key.
    pub fn validate(&self, sections: &[&Section]) -> Result<()> {
        let mut top = self.table.clone();
        for section in sections {
            top.remove(section.name);
        }
        crate::config::check_top_level(&top)
            .with_context(|| format!("in config file {}", self.path.display()))?;
        for section in sections {
            let Some(table) = self.section(section)? else {
                continue;
            };
            for (key, value) in table {
                self.check(section, key, value)?;
            }
        }
        Ok(())
    }

    fn section(&self, section: &Section) -> Result<Option<&toml::Table>> {
        match self.table.get(section.name) {
            None => Ok(None),
            Some(toml::Value::Table(table)) => Ok(Some(table)),
            Some(_) => bail!(
                "in config file {}: `{}` must be a table (`[{}]`)",
                self.path.display(),
                section.name,
                section.name
            ),
        }
    }

    /// Checks one key of `[section]`; returns the flags it stands for.
    fn check(&self, section: &Section, key: &str, value: &toml::Value) -> Result<Vec<OsString>> {
        let name = section.name;
        let file = self.path.display();
        if RUN_KEYS.contains(&key) {
            bail!(
                "`[{name}] {key}` in config file {file}: `{key}` is a run key; set it at the top \
                 level of the file"
            );
        }
        if key == "set" {
            bail!(
                "`[{name}] set` in config file {file}: agent hyperparameters go in the `[agent]` \
                 table"
            );
        }
        let known = section.keys();
        if !known.iter().any(|k| k == key) {
            bail!(
                "unknown key `[{name}] {key}` in config file {file} (known keys: {})",
                known.join(", ")
            );
        }
        let Some(arg) = section.arg(key) else {
            return Ok(Vec::new());
        };
        let invalid = |reason: String| {
            anyhow!("invalid value for `[{name}] {key}` in config file {file}: {reason}")
        };
        let args = to_args(arg, value).map_err(invalid)?;
        if args.is_empty() {
            return Ok(args);
        }
        // Through the flag's own parser. Relations between flags (requires, conflicts) are
        // checked by the full parse, not key by key.
        let probe = section
            .command()
            .expect("a section with an arg has a command")
            .clone()
            .mut_args(|a| a.env(None::<&str>))
            .no_binary_name(true);
        match probe.try_get_matches_from(&args) {
            Err(e)
                if !matches!(
                    e.kind(),
                    ErrorKind::MissingRequiredArgument | ErrorKind::ArgumentConflict
                ) =>
            {
                Err(invalid(first_line(&e)))
            }
            _ => Ok(args),
        }
    }

    /// The flags that give `[section]`'s values to the keys that `matches` has from neither
    /// the command line nor the environment. Call [`validate`](Self::validate) first.
    pub fn args_for(&self, section: &Section, matches: &ArgMatches) -> Result<Vec<OsString>> {
        let Some(table) = self.section(section)? else {
            return Ok(Vec::new());
        };
        let mut args = Vec::new();
        for (key, value) in table {
            let Some(arg) = section.arg(key) else {
                continue;
            };
            let explicit = matches!(
                matches.value_source(arg.get_id().as_str()),
                Some(ValueSource::CommandLine | ValueSource::EnvVariable)
            );
            if !explicit {
                args.extend(self.check(section, key, value)?);
            }
        }
        Ok(args)
    }
}

/// The flags a file value stands for: `--key=value` (once per element for a repeatable flag),
/// `--key` for a true switch, nothing for a false one.
fn to_args(arg: &Arg, value: &toml::Value) -> Result<Vec<OsString>, String> {
    let flag = format!("--{}", arg.get_long().unwrap_or_default());
    let action = arg.get_action();
    if !action.takes_values() {
        let toml::Value::Boolean(on) = value else {
            return Err(format!("expected true or false, got {value}"));
        };
        let set = match action {
            ArgAction::SetFalse => !on,
            _ => *on,
        };
        return Ok(if set { vec![flag.into()] } else { Vec::new() });
    }
    let scalar = |v: &toml::Value| match v {
        toml::Value::String(s) => Ok(s.clone()),
        toml::Value::Integer(i) => Ok(i.to_string()),
        toml::Value::Float(f) => Ok(f.to_string()),
        toml::Value::Boolean(b) => Ok(b.to_string()),
        toml::Value::Datetime(d) => Ok(d.to_string()),
        other => Err(format!("expected a single value, got {other}")),
    };
    let values = match value {
        toml::Value::Array(items) if matches!(action, ArgAction::Append) => {
            items.iter().map(scalar).collect::<Result<Vec<_>, _>>()?
        }
        other => vec![scalar(other)?],
    };
    Ok(values
        .into_iter()
        .map(|v| format!("{flag}={v}").into())
        .collect())
}

/// A clap error's message without the `error: ` prefix and the usage hints.
fn first_line(e: &clap::Error) -> String {
    let text = e.render().to_string();
    let line = text.lines().next().unwrap_or_default();
    line.strip_prefix("error: ").unwrap_or(line).to_string()
}

/// A daemon's table with every key's resolved value, as TOML (keys without a value are
/// comments), for `--print-config`.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct ResolvedSection {
    text: String,
}

impl ResolvedSection {
    fn of(section: &Section, matches: &ArgMatches) -> Self {
        let mut text = format!("[{}]\n", section.name);
        let Some(cmd) = section.command() else {
            return Self { text };
        };
        for arg in cmd.get_arguments() {
            let Some(key) = key_of(arg) else { continue };
            let id = arg.get_id().as_str();
            let raw: Vec<String> = matches
                .get_raw(id)
                .map(|values| values.map(|v| v.to_string_lossy().into_owned()).collect())
                .unwrap_or_default();
            let line = if !arg.get_action().takes_values() {
                let on = raw.first().is_some_and(|v| v == "true");
                format!("{key} = {on}")
            } else if matches!(arg.get_action(), ArgAction::Append) {
                let items: Vec<String> = raw.iter().map(|v| typed(v).to_string()).collect();
                format!("{key} = [{}]", items.join(", "))
            } else if let Some(value) = raw.first() {
                format!("{key} = {}", typed(value))
            } else {
                let help = arg.get_help().map(|h| h.to_string()).unwrap_or_default();
                match default_note(&help) {
                    Some(note) => format!("# {key}: not set (default: {note})"),
                    None => format!("# {key}: not set"),
                }
            };
            text += &line;
            text.push('\n');
        }
        Self { text }
    }

    pub fn to_toml(&self) -> &str {
        &self.text
    }
}

/// A flag's text value as the TOML value a reader would write: numbers and booleans bare,
/// anything else a string (the daemon reads them all back through the flag's parser).
fn typed(value: &str) -> toml::Value {
    if let Ok(i) = value.parse::<i64>() {
        return toml::Value::Integer(i);
    }
    if value.contains(['.', 'e'])
        && value.chars().all(|c| "0123456789.e-+".contains(c))
        && let Ok(f) = value.parse::<f64>()
    {
        return toml::Value::Float(f);
    }
    match value {
        "true" => toml::Value::Boolean(true),
        "false" => toml::Value::Boolean(false),
        _ => toml::Value::String(value.to_string()),
    }
}

/// Where a daemon's arguments sit in a command line: the subcommands leading to them (none for
/// a daemon's own binary, `["learner"]` for `hac learner`) and its table.
#[derive(Debug, Clone, Copy)]
pub struct Mount<'a> {
    pub path: &'a [&'a str],
    pub section: &'a Section,
}

/// Parses the process's command line as `C`, applying the config file when the command run is
/// one of `daemons` (see the module docs); `others` are the other tables to check. Returns the
/// daemon's resolved table for `--print-config`. Clap's own errors (and `--help`) exit here.
pub fn parse<C: Parser>(
    daemons: &[Mount<'_>],
    others: &[&Section],
) -> Result<(C, Option<ResolvedSection>)> {
    parse_from(std::env::args_os().collect(), daemons, others)
}

/// [`parse`] with the command line given.
pub fn parse_from<C: Parser>(
    argv: Vec<OsString>,
    daemons: &[Mount<'_>],
    others: &[&Section],
) -> Result<(C, Option<ResolvedSection>)> {
    let mut cmd = C::command();
    for mount in daemons {
        cmd = at_path_mut(cmd, mount.path);
    }
    let matches = cmd
        .clone()
        .try_get_matches_from(&argv)
        .unwrap_or_else(|e| exit_naming_variable(e, &argv, daemons));
    let Some(mount) = daemons.iter().find(|m| at_path(&matches, m.path).is_some()) else {
        let cli = C::from_arg_matches(&matches).unwrap_or_else(|e| e.exit());
        return Ok((cli, None));
    };
    let daemon = at_path(&matches, mount.path).expect("found above");
    let matches = match daemon.try_get_one::<PathBuf>("config").ok().flatten() {
        None => matches,
        Some(path) => {
            let file = ConfigFile::load(path)?;
            let sections: Vec<&Section> = daemons
                .iter()
                .map(|m| m.section)
                .chain(others.iter().copied())
                .collect();
            file.validate(&sections)?;
            let extra = file.args_for(mount.section, daemon)?;
            if extra.is_empty() {
                matches
            } else {
                cmd.try_get_matches_from(argv.into_iter().chain(extra))
                    .map_err(|e| anyhow!("in config file {}: {}", path.display(), first_line(&e)))?
            }
        }
    };
    let daemon = at_path(&matches, mount.path).expect("the same command line, parsed again");
    let resolved = ResolvedSection::of(mount.section, daemon);
    let cli = C::from_arg_matches(&matches).unwrap_or_else(|e| e.exit());
    Ok((cli, Some(resolved)))
}

/// Exits with clap's error; an invalid value that came from a `HAC_*` variable is reported as
/// the variable's (clap names only the flag).
fn exit_naming_variable(e: clap::Error, argv: &[OsString], daemons: &[Mount<'_>]) -> ! {
    use clap::error::{ContextKind, ContextValue};
    if matches!(
        e.kind(),
        ErrorKind::InvalidValue | ErrorKind::ValueValidation
    ) && let Some(ContextValue::String(shown)) = e.get(ContextKind::InvalidArg)
    {
        let long = shown
            .trim_start_matches("--")
            .split([' ', '='])
            .next()
            .unwrap_or_default();
        let on_command_line = argv.iter().any(|a| {
            let a = a.to_string_lossy();
            a == format!("--{long}") || a.starts_with(&format!("--{long}="))
        });
        let from_env = daemons.iter().find_map(|m| {
            let cmd = m.section.command()?;
            let arg = cmd.get_arguments().find(|a| a.get_long() == Some(long))?;
            let var = arg.get_env()?;
            std::env::var_os(var)?;
            Some((
                var.to_string_lossy().into_owned(),
                key_of(arg),
                m.section.name,
            ))
        });
        if let (false, Some((var, key, section))) = (on_command_line, from_env) {
            let key = key.map_or(String::new(), |k| format!(", `[{section}] {k}`"));
            eprintln!(
                "error: invalid value in environment variable {var} (flag `--{long}`{key}): {}",
                first_line(&e)
            );
            std::process::exit(2);
        }
    }
    e.exit()
}

/// The matches of the subcommand at `path`, if that is the one given.
fn at_path<'a>(matches: &'a ArgMatches, path: &[&str]) -> Option<&'a ArgMatches> {
    path.iter()
        .try_fold(matches, |m, name| match m.subcommand() {
            Some((n, sub)) if n == *name => Some(sub),
            _ => None,
        })
}

/// `cmd` with the `HAC_*` variables added to the daemon at `path`.
fn at_path_mut(cmd: Command, path: &[&str]) -> Command {
    match path.split_first() {
        None => with_env_vars(cmd),
        Some((first, rest)) => cmd.mut_subcommand(first, |sub| at_path_mut(sub, rest)),
    }
}

#[cfg(test)]
mod tests {
    use clap::Args as _;

    use super::*;

    /// A daemon's flags, in the shapes the real daemons use.
    #[derive(Debug, clap::Args)]
    struct DemoArgs {
        /// Run key.
        #[arg(long, env = "HAC_ENV")]
        env: Option<String>,
        #[command(flatten)]
        config: ConfigArgs,
        /// Where to listen.
        #[arg(long, env = "HAC_LISTEN", default_value = "127.0.0.1:50051")]
        listen: std::net::SocketAddr,
        /// Bounded.
        #[arg(long, default_value_t = 10, value_parser = clap::value_parser!(u64).range(1..=100))]
        window: u64,
        /// Optional [default: the run's].
        #[arg(long)]
        every: Option<u64>,
        /// A switch.
        #[arg(long)]
        resume: bool,
        /// Repeatable.
        #[arg(long = "tag")]
        tag: Vec<String>,
    }

    #[derive(Debug, clap::Parser)]
    struct DemoCli {
        #[command(flatten)]
        args: DemoArgs,
    }

    fn section() -> Section {
        Section::of_flags("demo", DemoArgs::augment_args(Command::new("demo")))
    }

    fn file(name: &str, text: &str) -> PathBuf {
        let path = std::env::temp_dir().join(format!(
            "hac-daemon-test-{}-{name}.toml",
            std::process::id()
        ));
        std::fs::write(&path, text).unwrap();
        path
    }

    fn parse_demo(argv: &[&str]) -> Result<(DemoCli, Option<ResolvedSection>)> {
        let section = section();
        let other = Section::of_keys("other", &["alpha", "beta"]);
        let argv = std::iter::once("demo")
            .chain(argv.iter().copied())
            .map(OsString::from)
            .collect();
        parse_from(
            argv,
            &[Mount {
                path: &[],
                section: &section,
            }],
            &[&other],
        )
    }

    #[test]
    fn keys_are_the_flags_but_run_keys_and_command_line_ones() {
        assert_eq!(
            section().keys(),
            ["listen", "window", "every", "resume", "tag"]
        );
        let cmd = section();
        let env = |key| {
            cmd.arg(key)
                .unwrap()
                .get_env()
                .map(|e| e.to_string_lossy().into_owned())
        };
        assert_eq!(env("window").as_deref(), Some("HAC_WINDOW"));
        assert_eq!(env("listen").as_deref(), Some("HAC_LISTEN"));
        let md = cmd.markdown();
        assert!(
            md.contains("| `window` | `--window` / `HAC_WINDOW` | `10` | Bounded |"),
            "{md}"
        );
        assert!(
            md.contains("| `every` | `--every` / `HAC_EVERY` | the run's | Optional |"),
            "{md}"
        );
    }

    #[test]
    fn file_values_fill_what_flags_and_variables_leave_unset() {
        let path = file(
            "fill",
            "env = \"pendulum\"\n[demo]\nwindow = 20\nresume = true\ntag = [\"a\", \"b\"]\nlisten = \"127.0.0.1:7\"\n[other]\nalpha = 1\n",
        );
        let p = path.to_str().unwrap();
        let (cli, resolved) = parse_demo(&["--config", p, "--listen", "127.0.0.1:9"]).unwrap();
        assert_eq!(cli.args.window, 20);
        assert!(cli.args.resume);
        assert_eq!(cli.args.tag, ["a", "b"]);
        assert_eq!(cli.args.listen.port(), 9, "the flag wins over the file");
        assert_eq!(cli.args.env, None, "run keys are resolved elsewhere");
        let text = resolved.unwrap();
        let text = text.to_toml();
        assert!(text.starts_with("[demo]\n"), "{text}");
        for line in [
            "listen = \"127.0.0.1:9\"",
            "window = 20",
            "# every: not set (default: the run's)",
            "resume = true",
            "tag = [\"a\", \"b\"]",
        ] {
            assert!(text.contains(line), "{line} in\n{text}");
        }
        // The printed table parses back to the same values.
        let printed = file("printed", text);
        let (again, _) = parse_demo(&["--config", printed.to_str().unwrap()]).unwrap();
        assert_eq!(again.args.listen.port(), 9);
        assert_eq!((again.args.window, again.args.resume), (20, true));
        let _ = std::fs::remove_file(printed);
        let _ = std::fs::remove_file(path);
    }

    #[test]
    fn every_bad_key_or_value_is_named_with_the_file() {
        let cases = [
            ("[demo]\nwindwo = 3\n", "unknown key `[demo] windwo`"),
            ("[other]\ngamma = 3\n", "unknown key `[other] gamma`"),
            ("[demo]\nwindow = 0\n", "invalid value for `[demo] window`"),
            (
                "[demo]\nwindow = \"many\"\n",
                "invalid value for `[demo] window`",
            ),
            (
                "[demo]\nresume = \"yes\"\n",
                "invalid value for `[demo] resume`",
            ),
            (
                "[demo]\nlisten = [1, 2]\n",
                "invalid value for `[demo] listen`",
            ),
            ("[demo]\nenv = \"pendulum\"\n", "`env` is a run key"),
            ("[demo]\nset = [\"gamma=0.9\"]\n", "[agent]"),
            ("levls = 2\n", "levls"),
            ("demo = 3\n", "`demo` must be a table"),
            ("[demo\n", "config file"),
        ];
        for (i, (text, expected)) in cases.iter().enumerate() {
            let path = file(&format!("bad{i}"), text);
            let e = format!(
                "{:#}",
                parse_demo(&["--config", path.to_str().unwrap()]).unwrap_err()
            );
            assert!(e.contains(expected), "{text:?}: {e}");
            assert!(
                e.contains(path.to_str().unwrap()),
                "{text:?} names the file: {e}"
            );
            let _ = std::fs::remove_file(path);
        }
    }
}
