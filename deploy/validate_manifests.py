#!/usr/bin/env python3
"""Offline checks of the deployment files (run by deploy/validate.sh, which sets up the venv).

1. Every document of deploy/k8s/*.yaml against the Kubernetes JSON schemas bundled in the
   `kubernetes-validate` package, in strict mode (unknown fields are errors), for the oldest
   supported Kubernetes version (1.27: native gRPC probes are GA) and the newest bundled one.
   ServiceMonitor (a CRD) against deploy/schemas/servicemonitor-monitoring-v1.json. A
   Kustomization has no schema: its resource list is checked instead.
2. Cross-references the schemas cannot see: selectors and pod labels, named ports, probes,
   the drain deadline against the grace period, the HPA metric against the prometheus-adapter
   rule, the ConfigMap's TOML (parses, and every key is one of deploy/mpiflow.toml's when that
   file exists).
3. deploy/compose.yaml parses and runs 3 replicas.
4. A negative self-test: broken copies of the Deployment must be rejected, else the check is
   not checking anything.

Prints one line per check and ends with `validate: N passed, M failed`; exit 1 on any failure.
"""

from __future__ import annotations

import copy
import glob
import json
import os
import re
import sys

import jsonschema
import yaml
from kubernetes_validate import utils as kv

try:
    import tomllib  # Python >= 3.11
except ModuleNotFoundError:  # pragma: no cover
    import tomli as tomllib  # type: ignore

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
K8S = os.path.join(ROOT, "deploy", "k8s")
SCHEMAS = os.path.join(ROOT, "deploy", "schemas")
MIN_K8S = "1.27.0"
CRD_SCHEMAS = {
    ("monitoring.coreos.com/v1", "ServiceMonitor"): "servicemonitor-monitoring-v1.json",
}

passed = 0
failed = 0


def ok(what: str) -> None:
    global passed
    passed += 1
    print(f"ok    {what}")


def fail(what: str, why: str) -> None:
    global failed
    failed += 1
    print(f"FAIL  {what}: {why}")


def skip(what: str, why: str) -> None:
    print(f"skip  {what}: {why}")


def k8s_versions() -> list[str]:
    return [MIN_K8S, kv.latest_version()]


def schema_errors(doc: dict) -> list[str]:
    """Validation errors of one document (empty = valid)."""
    key = (doc.get("apiVersion"), doc.get("kind"))
    if key in CRD_SCHEMAS:
        with open(os.path.join(SCHEMAS, CRD_SCHEMAS[key])) as f:
            schema = json.load(f)
        v = jsonschema.Draft202012Validator(schema)
        return [f"{'/'.join(map(str, e.absolute_path)) or '.'}: {e.message}" for e in v.iter_errors(doc)]
    errors = []
    for version in k8s_versions():
        try:
            kv.validate(doc, version, strict=True)
        except kv.ValidationError as e:
            path = "/".join(map(str, e.absolute_path)) or "."
            errors.append(f"k8s {version}: {path}: {e.message}")
        except kv.SchemaNotFoundError as e:
            errors.append(e.message)
    return errors


def load_docs() -> list[tuple[str, dict]]:
    docs = []
    for path in sorted(glob.glob(os.path.join(K8S, "*.yaml"))):
        rel = os.path.relpath(path, ROOT)
        try:
            with open(path) as f:
                loaded = [d for d in yaml.safe_load_all(f) if d is not None]
        except yaml.YAMLError as e:
            fail(rel, f"not YAML: {e}")
            continue
        if not loaded:
            fail(rel, "no documents")
        for d in loaded:
            if not isinstance(d, dict) or "kind" not in d or "apiVersion" not in d:
                fail(rel, "a document without apiVersion/kind")
                continue
            docs.append((rel, d))
    return docs


def name_of(rel: str, d: dict) -> str:
    return f"{rel} {d['kind']}" + (f"/{d['metadata']['name']}" if d.get('metadata', {}).get('name') else "")


def check_schemas(docs: list[tuple[str, dict]]) -> None:
    for rel, d in docs:
        what = name_of(rel, d)
        if d["kind"] == "Kustomization":
            missing = [r for r in d.get("resources", []) if not os.path.exists(os.path.join(K8S, r))]
            if missing:
                fail(what, f"resources not found: {missing}")
            else:
                skip(what, "no Kubernetes schema for kustomize's own file")
                ok(f"{what}: its {len(d.get('resources', []))} resources exist")
            continue
        errs = schema_errors(d)
        if errs:
            fail(what, "; ".join(errs[:5]))
        else:
            key = (d["apiVersion"], d["kind"])
            against = f"vendored CRD schema {CRD_SCHEMAS[key]}" if key in CRD_SCHEMAS else \
                f"Kubernetes {' and '.join(v.rsplit('.', 1)[0] for v in k8s_versions())} schemas (strict)"
            ok(f"{what} against {against}")


def one(docs, kind, name=None):
    found = [d for _, d in docs if d["kind"] == kind and (name is None or d["metadata"]["name"] == name)]
    return found[0] if found else None


def selector_matches(selector: dict, labels: dict) -> bool:
    return all(labels.get(k) == v for k, v in selector.get("matchLabels", {}).items())


def toml_keys(table: dict, prefix: str = "") -> list[str]:
    keys = []
    for k, v in table.items():
        full = f"{prefix}{k}"
        keys.append(full)
        if isinstance(v, dict):
            keys += toml_keys(v, full + ".")
    return keys


def check_config_keys(text: str) -> list[str]:
    """Keys of the ConfigMap's TOML that deploy/mpiflow.toml (the server's documented example)
    does not mention, as a key or a commented key."""
    example_path = os.path.join(ROOT, "deploy", "mpiflow.toml")
    if not os.path.exists(example_path):
        return []
    with open(example_path) as f:
        example = f.read()
    unknown = []
    cfg = tomllib.loads(text)
    for key in cfg:
        leaf = key
        if not re.search(rf"^\s*#?\s*(\[\[?)?{re.escape(leaf)}(\]\]?|\s*=)", example, re.M):
            unknown.append(key)
    for table in ("models", "sample"):
        for key in cfg.get(table, {}) if isinstance(cfg.get(table), dict) else {}:
            if not re.search(rf"^\s*#?\s*{re.escape(key)}\s*=", example, re.M):
                unknown.append(f"{table}.{key}")
    for ds in cfg.get("datasets", []):
        for key in ds:
            if key not in ("name", "path", "sample"):
                unknown.append(f"datasets.{key}")
    return unknown


def check_references(docs: list[tuple[str, dict]]) -> None:
    dep = one(docs, "Deployment", "mpiflow")
    svc = one(docs, "Service", "mpiflow")
    if dep is None or svc is None:
        fail("references", "Deployment/mpiflow or Service/mpiflow missing")
        return
    pod = dep["spec"]["template"]
    labels = pod["metadata"].get("labels", {})
    spec = pod["spec"]
    c = spec["containers"][0]
    port_names = {p["name"]: p["containerPort"] for p in c.get("ports", [])}

    def check(what: str, cond: bool, why: str) -> None:
        ok(what) if cond else fail(what, why)

    check("Deployment selector matches its pod labels", selector_matches(dep["spec"]["selector"], labels),
          f"{dep['spec']['selector']} vs {labels}")
    check("Service is headless", svc["spec"].get("clusterIP") == "None", "clusterIP is not None")
    check("Service selects the pods", all(labels.get(k) == v for k, v in svc["spec"]["selector"].items()),
          f"{svc['spec']['selector']} vs {labels}")
    bad_ports = [p["targetPort"] for p in svc["spec"]["ports"]
                 if isinstance(p["targetPort"], str) and p["targetPort"] not in port_names]
    check("Service targetPorts are container port names", not bad_ports, f"unknown: {bad_ports}")

    grpc_port = port_names.get("grpc")
    # with TLS the probes go to the plaintext health-only listener (port "health", health_addr):
    # the kubelet's gRPC probe cannot do TLS
    probe_port = port_names.get("health", grpc_port)
    probes = {k: c.get(k) for k in ("startupProbe", "readinessProbe", "livenessProbe")}
    check("probes are native gRPC probes on the health (else grpc) port",
          all(p and "grpc" in p and p["grpc"]["port"] == probe_port for p in probes.values()),
          f"{probes}")
    rp = (probes["readinessProbe"] or {}).get("grpc", {})
    check("readiness asks for service mpiflow.v1.MpiFlow", rp.get("service") == "mpiflow.v1.MpiFlow",
          f"service = {rp.get('service')!r}")
    sc = {**spec.get("securityContext", {}), **c.get("securityContext", {})}
    check("runs as non-root", sc.get("runAsNonRoot") is True and sc.get("runAsUser", 0) != 0, f"{sc}")
    check("has resource requests and limits",
          bool(c.get("resources", {}).get("requests")) and bool(c.get("resources", {}).get("limits")), "missing")

    # the configuration
    cm_name = next((v["configMap"]["name"] for v in spec.get("volumes", []) if "configMap" in v), None)
    cm = one(docs, "ConfigMap", cm_name) if cm_name else None
    if cm is None or "mpiflow.toml" not in cm.get("data", {}):
        fail("ConfigMap with mpiflow.toml", f"the Deployment mounts {cm_name!r}, which has no mpiflow.toml")
        return
    text = cm["data"]["mpiflow.toml"]
    try:
        cfg = tomllib.loads(text)
        ok("ConfigMap mpiflow.toml is TOML")
    except tomllib.TOMLDecodeError as e:
        fail("ConfigMap mpiflow.toml is TOML", str(e))
        return
    unknown = check_config_keys(text)
    if os.path.exists(os.path.join(ROOT, "deploy", "mpiflow.toml")):
        check("ConfigMap keys are keys of deploy/mpiflow.toml", not unknown, f"unknown keys: {unknown}")
    else:
        skip("ConfigMap keys", "deploy/mpiflow.toml does not exist yet")
    addr_port = int(str(cfg.get("addr", ":50051")).rsplit(":", 1)[1])
    check("config addr port = container port grpc", addr_port == grpc_port, f"{addr_port} vs {grpc_port}")
    if "metrics_addr" in cfg:
        mport = int(str(cfg["metrics_addr"]).rsplit(":", 1)[1])
        check("config metrics_addr port = container port metrics", mport == port_names.get("metrics"),
              f"{mport} vs {port_names.get('metrics')}")
    if "health" in port_names or "health_addr" in cfg:
        hport = int(str(cfg.get("health_addr", ":0")).rsplit(":", 1)[1])
        check("config health_addr port = container port health", hport == port_names.get("health"),
              f"{hport} vs {port_names.get('health')}")
    drain = float(cfg.get("drain_timeout_s", 10.0))
    pre = 0
    cmd = (c.get("lifecycle", {}).get("preStop", {}).get("exec", {}) or {}).get("command", [])
    if len(cmd) == 2 and cmd[0] == "sleep":
        pre = float(cmd[1])
    grace = spec.get("terminationGracePeriodSeconds", 30)
    check(f"grace period {grace} s > preStop {pre:g} s + drain {drain:g} s", grace > pre + drain,
          "the kubelet would SIGKILL before the drain ends")

    # disruption budget, monitoring, autoscaling
    pdb = one(docs, "PodDisruptionBudget")
    check("PodDisruptionBudget selects the pods", pdb is not None and selector_matches(pdb["spec"]["selector"], labels),
          "missing or not matching")
    sm = one(docs, "ServiceMonitor")
    if sm is not None:
        svc_ports = {p["name"] for p in svc["spec"]["ports"]}
        check("ServiceMonitor selects the Service and its metrics port",
              selector_matches(sm["spec"]["selector"], svc["metadata"].get("labels", {}))
              and all(e.get("port") in svc_ports for e in sm["spec"]["endpoints"]),
              "selector or port does not match")
    ann = pod["metadata"].get("annotations", {})
    check("scrape annotations point at the metrics port",
          ann.get("prometheus.io/scrape") == "true" and ann.get("prometheus.io/port") == str(port_names.get("metrics")),
          f"{ann}")
    hpa = one(docs, "HorizontalPodAutoscaler")
    if hpa is None:
        fail("HorizontalPodAutoscaler", "missing")
        return
    check("HPA scales the Deployment", hpa["spec"]["scaleTargetRef"]["name"] == dep["metadata"]["name"], "wrong target")
    metric_names = [m["pods"]["metric"]["name"] for m in hpa["spec"].get("metrics", []) if m["type"] == "Pods"]
    adapter = next((d for _, d in docs if d["kind"] == "ConfigMap" and "config.yaml" in d.get("data", {})
                    and "rules" in (yaml.safe_load(d["data"]["config.yaml"]) or {})), None)
    if adapter is None:
        fail("prometheus-adapter rules", "no ConfigMap with config.yaml rules")
        return
    rules = yaml.safe_load(adapter["data"]["config.yaml"])["rules"]
    published = {r["name"]["as"] for r in rules}
    well_formed = all({"seriesQuery", "resources", "name", "metricsQuery"} <= set(r) for r in rules)
    check("prometheus-adapter rules are well-formed", well_formed, "a rule lacks seriesQuery/resources/name/metricsQuery")
    check(f"HPA pods metrics {metric_names} are published by the adapter rules",
          bool(metric_names) and set(metric_names) <= published, f"published: {sorted(published)}")


def check_compose() -> None:
    path = os.path.join(ROOT, "deploy", "compose.yaml")
    if not os.path.exists(path):
        fail("deploy/compose.yaml", "missing")
        return
    with open(path) as f:
        c = yaml.safe_load(f)
    svc = (c or {}).get("services", {})
    replicas = sum(s.get("deploy", {}).get("replicas", 1) for s in svc.values() if "mpiflow" in str(s.get("image", "")))
    if replicas == 3:
        ok("deploy/compose.yaml: 3 mpiflow replicas")
    else:
        fail("deploy/compose.yaml", f"{replicas} mpiflow replicas, expected 3")


def negative_self_test(docs: list[tuple[str, dict]]) -> None:
    dep = one(docs, "Deployment", "mpiflow")
    if dep is None:
        return
    breakages = {
        "replicas as a string": lambda d: d["spec"].__setitem__("replicas", "three"),
        "misspelt field (livenessProbe.grpcc)": lambda d: d["spec"]["template"]["spec"]["containers"][0]
        ["livenessProbe"].__setitem__("grpcc", d["spec"]["template"]["spec"]["containers"][0]["livenessProbe"]["grpc"]),
        "a container without a name": lambda d: d["spec"]["template"]["spec"]["containers"][0].pop("name"),
        "gRPC probe port as a name": lambda d: d["spec"]["template"]["spec"]["containers"][0]["readinessProbe"]
        ["grpc"].__setitem__("port", "grpc"),
    }
    caught = []
    for what, breakit in breakages.items():
        broken = copy.deepcopy(dep)
        breakit(broken)
        if schema_errors(broken):
            caught.append(what)
        else:
            fail("negative self-test", f"a Deployment with {what} was accepted")
    sm = one(docs, "ServiceMonitor")
    if sm is not None:
        broken = copy.deepcopy(sm)
        broken["spec"]["endpoints"][0]["intervall"] = "15s"
        if schema_errors(broken):
            caught.append("ServiceMonitor with a misspelt field")
        else:
            fail("negative self-test", "a ServiceMonitor with a misspelt field was accepted")
    if caught:
        ok(f"negative self-test: rejected {len(caught)} broken manifests ({', '.join(caught)})")


def check_bake_job(docs: list[tuple[str, dict]]) -> None:
    """The bake Job: Indexed, and its --shard argument's N equal to its completions."""
    job = one(docs, "Job", "mpiflow-bake")
    if job is None:
        fail("bake Job", "deploy/k8s/bake-job.yaml has no Job mpiflow-bake")
        return
    spec = job["spec"]
    if spec.get("completionMode") != "Indexed":
        fail("bake Job", f"completionMode {spec.get('completionMode')!r}, expected Indexed")
        return
    args = [a for c in spec["template"]["spec"]["containers"] for a in c.get("args", [])]
    shard = [a for a in args if a.startswith("--shard")]
    m = re.fullmatch(r"--shard[= ]\$\(JOB_COMPLETION_INDEX\)/(\d+)", shard[0]) if len(shard) == 1 else None
    if args[:1] != ["bake"] or m is None:
        fail("bake Job", f"args {args}: expected `bake ... --shard=$(JOB_COMPLETION_INDEX)/N`")
    elif int(m.group(1)) != spec.get("completions"):
        fail("bake Job", f"--shard .../{m.group(1)} but completions {spec.get('completions')}: items would be lost")
    else:
        ok(f"bake Job: Indexed, {spec['completions']} shards = completions, --shard from JOB_COMPLETION_INDEX")


def main() -> int:
    print(f"kubernetes-validate schemas: {MIN_K8S.rsplit('.', 1)[0]} and {kv.latest_version().rsplit('.', 1)[0]}")
    docs = load_docs()
    check_schemas(docs)
    check_references(docs)
    check_bake_job(docs)
    check_compose()
    if "--no-self-test" not in sys.argv:
        negative_self_test(docs)
    print(f"validate: {passed} passed, {failed} failed")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
