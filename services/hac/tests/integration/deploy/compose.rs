//! The Compose files: schema, and the services against the daemons.

use std::collections::BTreeMap;

use serde_json::Value;

use super::binaries::{
    Daemon, Process, check_env, flag_of_env, health_services, host_of, is_boolish, port_of,
};
use super::{deploy, json_file, read, strings, yaml_documents};

pub fn compose_validator() -> jsonschema::Validator {
    let schema = json_file(&deploy().join("schemas/compose-spec.json"));
    jsonschema::validator_for(&schema).expect("the Compose schema compiles")
}

pub fn compose_files() -> Vec<(&'static str, Value)> {
    ["compose.yaml", "compose.shm.yaml"]
        .into_iter()
        .map(|name| {
            let mut documents = yaml_documents(&read(&deploy().join(name)));
            assert_eq!(documents.len(), 1, "{name}: one YAML document");
            (name, documents.remove(0))
        })
        .collect()
}

pub fn compose_environment(service: &Value) -> BTreeMap<String, String> {
    match &service["environment"] {
        Value::Object(map) => map
            .iter()
            .map(|(k, v)| {
                (
                    k.clone(),
                    v.as_str().map_or_else(|| v.to_string(), str::to_string),
                )
            })
            .collect(),
        Value::Array(items) => items
            .iter()
            .filter_map(|i| i.as_str()?.split_once('='))
            .map(|(k, v)| (k.to_string(), v.to_string()))
            .collect(),
        _ => BTreeMap::new(),
    }
}

/// `hac health <url> --service <name>` from a Compose health check: (port, service).
pub fn compose_health_check(test: &Value) -> Result<(u16, String), String> {
    let argv = strings(test);
    let words: Vec<&str> = argv.iter().map(String::as_str).collect();
    let ["CMD", "hac", "health", rest @ ..] = words.as_slice() else {
        return Err(format!(
            "health check {argv:?} is not [CMD, hac, health, ...]"
        ));
    };
    let mut url = None;
    let mut service = String::new();
    let mut words = rest.iter();
    while let Some(word) = words.next() {
        match *word {
            "--service" => service = words.next().unwrap_or(&"").to_string(),
            w if w.starts_with("--service=") => service = w["--service=".len()..].to_string(),
            w if w.starts_with("--") => {
                words.next();
            }
            w => url = Some(w.to_string()),
        }
    }
    let url = url.ok_or("health check without a URL")?;
    let port = port_of(&url).ok_or_else(|| format!("health check URL {url} has no port"))?;
    Ok((port, service))
}

pub fn check_compose() -> Vec<String> {
    let mut problems = Vec::new();
    let files = compose_files();
    let (_, compose) = &files[0];
    let config_text = read(&deploy().join("hac.toml"));
    let config: toml::Table = toml::from_str(&config_text).unwrap();
    let services = compose["services"].as_object().expect("services");
    let mut daemons = BTreeMap::new();
    for (name, service) in services {
        let place = format!("compose.yaml/{name}");
        let mut argv = strings(&service["entrypoint"]);
        argv.extend(strings(&service["command"]));
        let Some((daemon, args)) = Daemon::of_command(&argv) else {
            problems.push(format!("{place}: runs {argv:?}"));
            continue;
        };
        let process = Process {
            place: place.clone(),
            daemon,
            args,
            env: compose_environment(service),
            config: config.clone(),
        };
        problems.extend(process.check_definitions());
        // The config: a Compose config whose file is deploy/hac.toml, mounted at HAC_CONFIG.
        let config_path = process.setting("config").unwrap_or_default();
        let mounted = service["configs"]
            .as_array()
            .into_iter()
            .flatten()
            .any(|c| {
                c["target"] == config_path.as_str()
                    && compose["configs"][c["source"].as_str().unwrap_or_default()]["file"]
                        == "./hac.toml"
            });
        if !mounted {
            problems.push(format!(
                "{place}: HAC_CONFIG `{config_path}` is not the config ./hac.toml"
            ));
        }
        // The token: the secret hac_token at its default path.
        let token = process.setting("token_file").unwrap_or_default();
        let has_secret = strings(&service["secrets"])
            .iter()
            .any(|s| s == "hac_token")
            && compose["secrets"]["hac_token"]["file"].is_string();
        if token != "/run/secrets/hac_token" || !has_secret {
            problems.push(format!(
                "{place}: the token must be the secret hac_token at /run/secrets/hac_token, not `{token}`"
            ));
        }
        let (port_key, ports_published) = match daemon {
            Daemon::Learner => ("listen", true),
            Daemon::Actor => ("status_listen", false),
        };
        let port = process.port(port_key);
        match compose_health_check(&service["healthcheck"]["test"]) {
            Ok((check_port, check_service)) => {
                if Some(check_port) != port
                    || !health_services(daemon).contains(&check_service.as_str())
                {
                    problems.push(format!(
                        "{place}: health check asks {check_port} about `{check_service}`; the daemon serves health on {port:?} for {:?}",
                        health_services(daemon)
                    ));
                }
            }
            Err(e) => problems.push(format!("{place}: {e}")),
        }
        if ports_published {
            let published: Vec<u16> = strings(&service["ports"])
                .iter()
                .filter_map(|p| p.rsplit(':').next()?.parse().ok())
                .collect();
            for key in ["listen", "metrics_listen"] {
                if !process.port(key).is_some_and(|p| published.contains(&p)) {
                    problems.push(format!(
                        "{place}: {key} port {:?} is not published ({published:?})",
                        process.port(key)
                    ));
                }
            }
            let out = process.setting("out").unwrap_or_default();
            let on_volume = strings(&service["volumes"]).iter().any(|v| {
                let mut parts = v.split(':');
                let (source, target) = (parts.next().unwrap(), parts.next().unwrap_or_default());
                compose["volumes"].get(source).is_some() && out.starts_with(&format!("{target}/"))
            });
            if !on_volume {
                problems.push(format!(
                    "{place}: the run directory `{out}` is not on a named volume"
                ));
            }
        } else {
            let url = process.setting("learner").unwrap_or_default();
            let learner_service = host_of(&url).unwrap_or_default();
            let learner_port = services
                .get(learner_service)
                .and_then(|s| {
                    let mut argv = strings(&s["entrypoint"]);
                    argv.extend(strings(&s["command"]));
                    Daemon::of_command(&argv)
                })
                .filter(|(d, _)| *d == Daemon::Learner)
                .map(|(daemon, args)| Process {
                    place: String::new(),
                    daemon,
                    args,
                    env: compose_environment(&services[learner_service]),
                    config: config.clone(),
                })
                .and_then(|learner| learner.port("listen"));
            if learner_port.is_none() || learner_port != port_of(&url) {
                problems.push(format!(
                    "{place}: the learner URL `{url}` is not the learner service's listen port"
                ));
            }
        }
        daemons.insert(name.clone(), process);
    }
    // The shared-memory variant, applied on top.
    let (_, shm) = &files[1];
    for (name, service) in shm["services"].as_object().expect("services") {
        let Some(base) = daemons.get(name) else {
            problems.push(format!(
                "compose.shm.yaml/{name}: not a service of compose.yaml"
            ));
            continue;
        };
        let env = compose_environment(service);
        for (variable, value) in &env {
            if let Err(e) = check_env(base.daemon, variable, value) {
                problems.push(format!("compose.shm.yaml/{name}: {e}"));
            }
        }
        let mounts_iceoryx = strings(&service["volumes"]).iter().any(|v| {
            v.ends_with(":/tmp/iceoryx2")
                && shm["volumes"].get(v.split(':').next().unwrap()).is_some()
        });
        if !mounts_iceoryx {
            problems.push(format!(
                "compose.shm.yaml/{name}: no shared /tmp/iceoryx2 volume"
            ));
        }
        match base.daemon {
            Daemon::Learner => {
                let on = env.iter().any(|(k, v)| {
                    flag_of_env(Daemon::Learner, k).as_deref() == Some("shm")
                        && is_boolish(v)
                        && v != "false"
                });
                if service["ipc"] != "shareable" || !service["shm_size"].is_string() || !on {
                    problems.push(format!(
                        "compose.shm.yaml/{name}: the learner needs ipc: shareable, a shm_size and shm on"
                    ));
                }
            }
            Daemon::Actor => {
                let transport = env
                    .iter()
                    .find(|(k, _)| flag_of_env(Daemon::Actor, k).as_deref() == Some("transport"));
                if service["ipc"] != "service:hac-learner"
                    || transport.map(|(_, v)| v.as_str()) != Some("shm")
                {
                    problems.push(format!(
                        "compose.shm.yaml/{name}: actors need ipc: service:hac-learner and transport shm"
                    ));
                }
            }
        }
    }
    problems
}
