//! Rendering the kustomize overlays, validating the objects against the vendored Kubernetes
//! schemas, and checking the manifests against the daemons.

use std::collections::{BTreeMap, BTreeSet, HashMap};
use std::path::{Path, PathBuf};
use std::process::Command;
use std::sync::OnceLock;

use serde_json::Value;

use super::binaries::{Daemon, Process, health_services, host_of, port_of, proto_services};
use super::{deploy, json_file, read, strings, yaml_documents};

pub fn kustomize(dir: &Path) -> Vec<Value> {
    let output = match Command::new("kubectl").arg("kustomize").arg(dir).output() {
        Ok(output) => output,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => panic!(
            "kubectl is not installed or not on PATH: the deploy tests render deploy/k8s with \
             `kubectl kustomize` (kubectl 1.32 or newer has kustomize built in); install it"
        ),
        Err(e) => panic!("running kubectl: {e}"),
    };
    assert!(
        output.status.success(),
        "kubectl kustomize {} failed:\n{}",
        dir.display(),
        String::from_utf8_lossy(&output.stderr)
    );
    yaml_documents(&String::from_utf8(output.stdout).unwrap())
}

/// Every overlay directory under deploy/k8s/overlays.
pub fn overlays() -> Vec<(String, Vec<Value>)> {
    let dir = deploy().join("k8s/overlays");
    let mut names: Vec<String> = std::fs::read_dir(&dir)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    names.sort();
    assert!(
        names.len() >= 2,
        "expected at least the dev and cluster overlays"
    );
    names
        .into_iter()
        .map(|name| {
            let objects = kustomize(&dir.join(&name));
            (name, objects)
        })
        .collect()
}

pub fn rendered() -> &'static [(String, Vec<Value>)] {
    static RENDERED: OnceLock<Vec<(String, Vec<Value>)>> = OnceLock::new();
    RENDERED.get_or_init(overlays)
}

/// The vendored Kubernetes schemas, one validator per kind.
pub struct KubeSchemas {
    dir: PathBuf,
    registry: jsonschema::Registry<'static>,
    validators: HashMap<String, jsonschema::Validator>,
}

impl KubeSchemas {
    pub fn load() -> Self {
        let dir = deploy().join("schemas/kubernetes-v1.32.0-strict");
        let definitions = json_file(&dir.join("_definitions.json"));
        let id = definitions["$id"].as_str().unwrap().to_string();
        let registry = jsonschema::Registry::new()
            .add(id, definitions)
            .unwrap()
            .prepare()
            .unwrap();
        Self {
            dir,
            registry,
            validators: HashMap::new(),
        }
    }

    /// The schema file's name for an object: `<kind>[-<group>]-<version>.json`, as in the
    /// kubernetes-json-schema layout.
    pub fn file_for(object: &Value) -> String {
        let kind = object["kind"].as_str().unwrap_or_default().to_lowercase();
        let api_version = object["apiVersion"].as_str().unwrap_or_default();
        match api_version.split_once('/') {
            Some((group, version)) => {
                let group = group.split('.').next().unwrap();
                format!("{kind}-{group}-{version}.json")
            }
            None => format!("{kind}-{api_version}.json"),
        }
    }

    pub fn validate(&mut self, object: &Value) -> Vec<String> {
        let file = Self::file_for(object);
        let path = self.dir.join(&file);
        if !path.is_file() {
            return vec![format!(
                "no vendored schema {file} for {} {}: add the kind to deploy/schemas/vendor.py",
                object["apiVersion"], object["kind"]
            )];
        }
        let validator = self.validators.entry(file).or_insert_with(|| {
            jsonschema::options()
                .with_registry(&self.registry)
                .build(&json_file(&path))
                .unwrap_or_else(|e| panic!("schema {}: {e}", path.display()))
        });
        validator
            .iter_errors(object)
            .map(|e| format!("at {}: {e}", e.instance_path()))
            .collect()
    }
}

pub fn by_kind<'a>(objects: &'a [Value], kind: &str) -> impl Iterator<Item = &'a Value> {
    objects
        .iter()
        .filter(move |o| o["kind"].as_str() == Some(kind))
}

pub fn named<'a>(objects: &'a [Value], kind: &str, name: &str) -> Option<&'a Value> {
    by_kind(objects, kind).find(|o| o["metadata"]["name"].as_str() == Some(name))
}

/// The config file a container reads: `HAC_CONFIG` (or `--config`) must be a file mounted from a
/// ConfigMap key.
pub fn mounted_config(
    objects: &[Value],
    pod: &Value,
    container: &Value,
    path: &str,
) -> Result<String, String> {
    let mount = container["volumeMounts"]
        .as_array()
        .into_iter()
        .flatten()
        .find(|m| {
            let at = m["mountPath"].as_str().unwrap_or_default();
            match m["subPath"].as_str() {
                Some(_) => at == path,
                None => path.starts_with(&format!("{at}/")),
            }
        })
        .ok_or_else(|| format!("nothing is mounted at the config path {path}"))?;
    let key = match mount["subPath"].as_str() {
        Some(key) => key.to_string(),
        None => path.rsplit('/').next().unwrap().to_string(),
    };
    let volume = pod["volumes"]
        .as_array()
        .into_iter()
        .flatten()
        .find(|v| v["name"] == mount["name"])
        .ok_or_else(|| format!("no volume {}", mount["name"]))?;
    let name = volume["configMap"]["name"]
        .as_str()
        .ok_or_else(|| format!("the config at {path} is not from a ConfigMap"))?;
    let map = named(objects, "ConfigMap", name).ok_or_else(|| format!("no ConfigMap {name}"))?;
    map["data"][&key]
        .as_str()
        .map(str::to_string)
        .ok_or_else(|| format!("ConfigMap {name} has no key {key}"))
}

/// The token file must be the key `token` of the Secret `hac-token`, mounted read-only.
pub fn check_token_mount(pod: &Value, container: &Value, path: &str) -> Result<(), String> {
    let (dir, file) = path
        .rsplit_once('/')
        .ok_or_else(|| format!("token file {path} is not a path"))?;
    let mount = container["volumeMounts"]
        .as_array()
        .into_iter()
        .flatten()
        .find(|m| m["mountPath"] == dir)
        .ok_or_else(|| format!("nothing is mounted at {dir} for the token file {path}"))?;
    let volume = pod["volumes"]
        .as_array()
        .into_iter()
        .flatten()
        .find(|v| v["name"] == mount["name"])
        .ok_or_else(|| format!("no volume {}", mount["name"]))?;
    let secret = &volume["secret"];
    if secret["secretName"] != "hac-token" {
        return Err(format!(
            "the token volume is {volume}, not the Secret hac-token"
        ));
    }
    let key = secret["items"]
        .as_array()
        .and_then(|items| items.iter().find(|i| i["path"] == file))
        .map_or(file, |i| i["key"].as_str().unwrap_or_default());
    if key != "token" {
        return Err(format!("the token file {path} is key `{key}`, not `token`"));
    }
    Ok(())
}

pub fn probes(container: &Value) -> Vec<(&'static str, u16, String)> {
    ["startupProbe", "livenessProbe", "readinessProbe"]
        .into_iter()
        .filter_map(|kind| {
            let grpc = &container[kind]["grpc"];
            grpc.is_object().then(|| {
                (
                    kind,
                    grpc["port"].as_u64().unwrap_or(0) as u16,
                    grpc["service"].as_str().unwrap_or_default().to_string(),
                )
            })
        })
        .collect()
}

pub fn container_ports(container: &Value) -> Vec<(String, u16)> {
    container["ports"]
        .as_array()
        .into_iter()
        .flatten()
        .map(|p| {
            (
                p["name"].as_str().unwrap_or_default().to_string(),
                p["containerPort"].as_u64().unwrap_or(0) as u16,
            )
        })
        .collect()
}

/// Checks one overlay's objects; returns the problems found.
pub fn check_kubernetes(overlay: &str, objects: &[Value], image_uid: u64) -> Vec<String> {
    let mut problems = Vec::new();
    let deploy_config = read(&deploy().join("hac.toml"));
    let proto = proto_services();
    let mut daemons_seen = BTreeSet::new();
    let mut images = BTreeSet::new();
    let secret = named(objects, "Secret", "hac-token");
    if let Some(secret) = secret
        && secret["data"]["token"].is_null()
        && secret["stringData"]["token"].is_null()
    {
        problems.push(format!("{overlay}: Secret hac-token has no key `token`"));
    }
    for workload in objects
        .iter()
        .filter(|o| matches!(o["kind"].as_str(), Some("StatefulSet" | "Deployment")))
    {
        let name = workload["metadata"]["name"].as_str().unwrap_or_default();
        let template = &workload["spec"]["template"];
        let pod = &template["spec"];
        let labels = &template["metadata"]["labels"];
        let annotations = &template["metadata"]["annotations"];
        let security = &pod["securityContext"];
        if security["runAsNonRoot"] != true || security["runAsUser"].as_u64() != Some(image_uid) {
            problems.push(format!(
                "{overlay}/{name}: the pod must run as non-root uid {image_uid} (the image's USER)"
            ));
        }
        let mut learner_in_pod: Option<(Process, &Value)> = None;
        let mut actors_in_pod = Vec::new();
        for container in pod["containers"].as_array().into_iter().flatten() {
            let cname = container["name"].as_str().unwrap_or_default();
            let place = format!("{overlay}/{name}/{cname}");
            images.insert(container["image"].as_str().unwrap_or_default().to_string());
            let mut argv = strings(&container["command"]);
            argv.extend(strings(&container["args"]));
            let Some((daemon, args)) = Daemon::of_command(&argv) else {
                problems.push(format!(
                    "{place}: runs {argv:?}, not hac-learner or hac-actor"
                ));
                continue;
            };
            daemons_seen.insert(daemon);
            let env: BTreeMap<String, String> = container["env"]
                .as_array()
                .into_iter()
                .flatten()
                .map(|e| {
                    (
                        e["name"].as_str().unwrap_or_default().to_string(),
                        e["value"].as_str().unwrap_or_default().to_string(),
                    )
                })
                .collect();
            let mut process = Process {
                place: place.clone(),
                daemon,
                args,
                env,
                config: toml::Table::new(),
            };
            problems.extend(process.check_definitions());
            match process.setting("config") {
                None => problems.push(format!("{place}: no config file (HAC_CONFIG)")),
                Some(path) => match mounted_config(objects, pod, container, &path) {
                    Ok(text) => {
                        if text != deploy_config {
                            problems.push(format!(
                                "{place}: the mounted config differs from deploy/hac.toml"
                            ));
                        }
                        match toml::from_str(&text) {
                            Ok(table) => process.config = table,
                            Err(e) => problems.push(format!("{place}: config: {e}")),
                        }
                    }
                    Err(e) => problems.push(format!("{place}: {e}")),
                },
            }
            match process.setting("token_file") {
                None => problems.push(format!("{place}: no token file (HAC_TOKEN_FILE)")),
                Some(path) => {
                    if let Err(e) = check_token_mount(pod, container, &path) {
                        problems.push(format!("{place}: {e}"));
                    }
                }
            }
            let ports = container_ports(container);
            let (port_key, port_name) = match daemon {
                Daemon::Learner => ("listen", "grpc"),
                Daemon::Actor => ("status_listen", "status"),
            };
            let Some(grpc_port) = process.port(port_key) else {
                problems.push(format!("{place}: no {port_key} address"));
                continue;
            };
            if !ports.iter().any(|(_, p)| *p == grpc_port) {
                problems.push(format!(
                    "{place}: {port_key} port {grpc_port} is not a container port {ports:?}"
                ));
            }
            if !ports
                .iter()
                .any(|(n, p)| *p == grpc_port && n.ends_with(port_name))
            {
                problems.push(format!(
                    "{place}: container port {grpc_port} should be named `{port_name}`"
                ));
            }
            let found = probes(container);
            if !found.iter().any(|(k, ..)| *k == "readinessProbe")
                || !found.iter().any(|(k, ..)| *k == "livenessProbe")
            {
                problems.push(format!("{place}: needs gRPC readiness and liveness probes"));
            }
            for (kind, port, service) in &found {
                if *port != grpc_port {
                    problems.push(format!(
                        "{place}: {kind} probes port {port}, the daemon serves health on {grpc_port}"
                    ));
                }
                if !health_services(daemon).contains(&service.as_str())
                    || !(service.is_empty() || proto.contains(service))
                {
                    problems.push(format!(
                        "{place}: {kind} asks about `{service}`, {} answers for {:?}",
                        daemon.binary(),
                        health_services(daemon)
                    ));
                }
            }
            match process.port("metrics_listen") {
                None => problems.push(format!("{place}: no metrics_listen address")),
                Some(metrics) => {
                    if !ports.iter().any(|(_, p)| *p == metrics) {
                        problems.push(format!(
                            "{place}: metrics port {metrics} is not a container port"
                        ));
                    }
                }
            }
            match daemon {
                Daemon::Learner => learner_in_pod = Some((process, container)),
                Daemon::Actor => actors_in_pod.push(process),
            }
        }
        // The pod's scrape annotations name the main daemon's metrics port.
        let main = learner_in_pod
            .as_ref()
            .map(|(p, _)| p)
            .or(actors_in_pod.first());
        if let Some(main) = main {
            let metrics = main.port("metrics_listen").map(|p| p.to_string());
            if annotations["prometheus.io/scrape"] != "true"
                || annotations["prometheus.io/path"] != "/metrics"
                || annotations["prometheus.io/port"].as_str() != metrics.as_deref()
            {
                problems.push(format!(
                    "{overlay}/{name}: Prometheus annotations {annotations} do not name metrics port {metrics:?} and /metrics"
                ));
            }
        }
        if let Some((learner, container)) = &learner_in_pod {
            check_learner_storage(overlay, name, workload, container, learner, &mut problems);
        }
        for actor in &actors_in_pod {
            check_actor_reaches_learner(
                objects,
                actor,
                labels,
                learner_in_pod.as_ref(),
                pod,
                &mut problems,
            );
        }
    }
    if daemons_seen.len() != 2 {
        problems.push(format!(
            "{overlay}: expected a learner and actors, found {daemons_seen:?}"
        ));
    }
    if images.len() != 1 {
        problems.push(format!(
            "{overlay}: every container should run the one hac image, found {images:?}"
        ));
    }
    for service in by_kind(objects, "Service") {
        check_service(objects, service, &mut problems);
    }
    for budget in by_kind(objects, "PodDisruptionBudget") {
        let selector = &budget["spec"]["selector"]["matchLabels"];
        let selects_something = objects
            .iter()
            .any(|o| labels_match(selector, &o["spec"]["template"]["metadata"]["labels"]));
        if !selects_something {
            problems.push(format!(
                "{overlay}: PodDisruptionBudget {} selects no pods",
                budget["metadata"]["name"]
            ));
        }
    }
    if !objects.iter().any(|o| {
        o["kind"] == "PodDisruptionBudget"
            && labels_match(
                &o["spec"]["selector"]["matchLabels"],
                &named(objects, "Deployment", "hac-actor").unwrap_or(&Value::Null)["spec"]
                    ["template"]["metadata"]["labels"],
            )
    }) {
        problems.push(format!("{overlay}: no PodDisruptionBudget for the actors"));
    }
    problems
}

pub fn labels_match(selector: &Value, labels: &Value) -> bool {
    selector.as_object().is_some_and(|selector| {
        !selector.is_empty() && selector.iter().all(|(k, v)| labels[k] == *v)
    })
}

/// The run directory (and its checkpoints) lives on the StatefulSet's persistent volume.
pub fn check_learner_storage(
    overlay: &str,
    name: &str,
    workload: &Value,
    container: &Value,
    learner: &Process,
    problems: &mut Vec<String>,
) {
    let claims: Vec<&str> = workload["spec"]["volumeClaimTemplates"]
        .as_array()
        .into_iter()
        .flatten()
        .filter_map(|c| c["metadata"]["name"].as_str())
        .collect();
    let out = learner.setting("out").unwrap_or_default();
    let on_volume = container["volumeMounts"]
        .as_array()
        .into_iter()
        .flatten()
        .any(|m| {
            claims.contains(&m["name"].as_str().unwrap_or_default())
                && out.starts_with(&format!("{}/", m["mountPath"].as_str().unwrap_or_default()))
        });
    if workload["kind"] != "StatefulSet" || !on_volume {
        problems.push(format!(
            "{overlay}/{name}: the learner's run directory `{out}` must be on a volumeClaimTemplate of a StatefulSet"
        ));
    }
}

/// An actor's `learner` URL must reach the learner: a Service selecting the learner pods on the
/// learner's port, or localhost inside the learner's own pod (and then shared memory is wired).
pub fn check_actor_reaches_learner(
    objects: &[Value],
    actor: &Process,
    actor_labels: &Value,
    learner_in_pod: Option<&(Process, &Value)>,
    pod: &Value,
    problems: &mut Vec<String>,
) {
    let place = &actor.place;
    let Some(url) = actor.setting("learner") else {
        problems.push(format!("{place}: no learner URL"));
        return;
    };
    let (Some(host), Some(port)) = (host_of(&url), port_of(&url)) else {
        problems.push(format!("{place}: learner URL `{url}` has no host:port"));
        return;
    };
    if let Some((learner, learner_container)) = learner_in_pod {
        if !matches!(host, "127.0.0.1" | "localhost") || learner.port("listen") != Some(port) {
            problems.push(format!(
                "{place}: inside the learner's pod, the learner is at 127.0.0.1:{:?}, not {url}",
                learner.port("listen")
            ));
        }
        if actor.setting("transport").as_deref() == Some("shm") {
            check_shared_memory(place, learner, learner_container, actor, pod, problems);
        }
        return;
    }
    let Some(service) = named(objects, "Service", host) else {
        problems.push(format!(
            "{place}: the learner URL's host `{host}` is no Service"
        ));
        return;
    };
    let learners: Vec<&Value> = objects
        .iter()
        .filter(|o| {
            labels_match(
                &service["spec"]["selector"],
                &o["spec"]["template"]["metadata"]["labels"],
            )
        })
        .collect();
    if learners.is_empty() || labels_match(&service["spec"]["selector"], actor_labels) {
        problems.push(format!(
            "{place}: Service {host} does not select the learner"
        ));
    }
    let service_port = service["spec"]["ports"]
        .as_array()
        .into_iter()
        .flatten()
        .find(|p| p["port"].as_u64() == Some(u64::from(port)));
    if service_port.is_none() {
        problems.push(format!("{place}: Service {host} has no port {port}"));
    }
}

/// Same-pod actors over iceoryx2: the learner has shm on, and both share a memory-backed
/// /dev/shm and /tmp/iceoryx2.
pub fn check_shared_memory(
    place: &str,
    learner: &Process,
    learner_container: &Value,
    actor: &Process,
    pod: &Value,
    problems: &mut Vec<String>,
) {
    if !learner.is_true("shm") {
        problems.push(format!("{place}: uses shm but the learner's shm is off"));
    }
    let volume_at = |container: &Value, path: &str| -> Option<String> {
        container["volumeMounts"]
            .as_array()?
            .iter()
            .find(|m| m["mountPath"] == path)
            .and_then(|m| m["name"].as_str().map(str::to_string))
    };
    let actor_container = pod["containers"]
        .as_array()
        .into_iter()
        .flatten()
        .find(|c| {
            actor
                .place
                .ends_with(&format!("/{}", c["name"].as_str().unwrap_or_default()))
        })
        .unwrap();
    for path in ["/dev/shm", "/tmp/iceoryx2"] {
        let (a, b) = (
            volume_at(learner_container, path),
            volume_at(actor_container, path),
        );
        let memory = pod["volumes"]
            .as_array()
            .into_iter()
            .flatten()
            .find(|v| Some(v["name"].as_str().unwrap_or_default()) == a.as_deref())
            .is_some_and(|v| {
                v["emptyDir"]["medium"] == "Memory" && v["emptyDir"]["sizeLimit"].is_string()
            });
        if a.is_none() || a != b || !memory {
            problems.push(format!(
                "{place}: {path} must be the same sized, memory-backed volume as the learner's"
            ));
        }
    }
}

/// Each Service port's target must be a port of the pods it selects.
pub fn check_service(objects: &[Value], service: &Value, problems: &mut Vec<String>) {
    let name = service["metadata"]["name"].as_str().unwrap_or_default();
    let pods: Vec<&Value> = objects
        .iter()
        .filter(|o| {
            labels_match(
                &service["spec"]["selector"],
                &o["spec"]["template"]["metadata"]["labels"],
            )
        })
        .map(|o| &o["spec"]["template"]["spec"])
        .collect();
    if pods.is_empty() {
        problems.push(format!("Service {name} selects no pods"));
    }
    for port in service["spec"]["ports"].as_array().into_iter().flatten() {
        let target = &port["targetPort"];
        let served = pods.iter().all(|pod| {
            pod["containers"].as_array().into_iter().flatten().any(|c| {
                container_ports(c).iter().any(|(n, p)| match target {
                    Value::String(t) => n == t,
                    Value::Number(t) => t.as_u64() == Some(u64::from(*p)),
                    _ => port["port"].as_u64() == Some(u64::from(*p)),
                })
            })
        });
        if !served {
            problems.push(format!(
                "Service {name}: port {} targets {target}, which its pods do not expose",
                port["name"]
            ));
        }
    }
}
