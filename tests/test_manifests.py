"""Deployment files under docker/: the Kubernetes manifests against the Kubernetes OpenAPI schemas
(kubernetes-validate, offline), and every file's references to the others and to the service
itself (labels, ports, probe routes, setting names and values, timeouts) checked in code."""

from __future__ import annotations

import copy
import os
import re
import shutil
import subprocess
from pathlib import Path

import kubernetes_validate
import pytest
import yaml
from fastapi.routing import iter_route_contexts

from service.app import create_app
from service.settings import ServiceSettings

DOCKER = Path(__file__).resolve().parents[1] / "docker"
K8S = DOCKER / "k8s"
# the oldest Kubernetes minor still commonly run, and the newest the library knows
K8S_VERSIONS = ["1.29.0", kubernetes_validate.latest_version()]
REPLICAS = ["stylestream-1", "stylestream-2"]


# ---- helpers ------------------------------------------------------------------------------------


def manifests() -> list[dict]:
    return [
        doc
        for path in sorted(K8S.glob("*.yaml"))
        if path.name != "kustomization.yaml"
        for doc in yaml.safe_load_all(path.read_text())
        if doc
    ]


def one(kind: str, name: str) -> dict:
    [found] = [m for m in manifests() if m["kind"] == kind and m["metadata"]["name"] == name]
    return found


def selects(selector: dict[str, str], labels: dict[str, str]) -> bool:
    return bool(selector) and all(labels.get(k) == v for k, v in selector.items())


def service_routes() -> set[str]:
    """Paths the app really serves (routes are registered without starting it), those of its
    included routers too (FastAPI keeps an included router whole in `app.routes`)."""
    return {
        path for route in iter_route_contexts(create_app(ServiceSettings(), models={}).routes) if (path := route.path)
    }


def settings_from_env(env: dict[str, str], monkeypatch) -> ServiceSettings:
    """The settings a server would build from `env`: every STYLESTREAM_* key must name a field."""
    fields = {f"STYLESTREAM_{name.upper()}" for name in ServiceSettings.model_fields}
    unknown = {k for k in env if k.startswith("STYLESTREAM_")} - fields
    assert not unknown, f"not settings: {sorted(unknown)}"
    for key in fields:
        monkeypatch.delenv(key, raising=False)
    for key, value in env.items():
        monkeypatch.setenv(key, str(value))
    return ServiceSettings(_env_file=None)


def dockerfile(instruction: str) -> str:
    [line] = re.findall(rf"^{instruction} (.+)$", (DOCKER / "Dockerfile").read_text(), re.M)
    return line.strip()


def nginx_seconds(value: str) -> float:
    match = re.fullmatch(r"(\d+)(ms|s|m|h)?", value)
    assert match, value
    return int(match[1]) * {"ms": 0.001, "s": 1, None: 1, "m": 60, "h": 3600}[match[2]]


# ---- Kubernetes ---------------------------------------------------------------------------------


@pytest.mark.parametrize("version", K8S_VERSIONS)
def test_every_manifest_is_valid_against_the_kubernetes_schema(version):
    docs = manifests()
    assert {d["kind"] for d in docs} >= {
        "ConfigMap",
        "Deployment",
        "Service",
        "Ingress",
        "HorizontalPodAutoscaler",
        "PodDisruptionBudget",
        "NetworkPolicy",
    }
    for doc in docs:
        kubernetes_validate.validate(doc, version, strict=True)  # raises ValidationError, naming the field


def test_the_schema_check_rejects_a_misspelt_field():
    """The validation above can fail: a typo in a known field is an error, not ignored."""
    broken = copy.deepcopy(one("Deployment", "stylestream"))
    broken["spec"]["template"]["spec"]["containers"][0]["livenesProbe"] = broken["spec"]["template"]["spec"][
        "containers"
    ][0].pop("livenessProbe")
    with pytest.raises(kubernetes_validate.ValidationError):
        kubernetes_validate.validate(broken, K8S_VERSIONS[-1], strict=True)


def test_kustomization_lists_every_manifest():
    listed = yaml.safe_load((K8S / "kustomization.yaml").read_text())["resources"]
    assert sorted(listed) == sorted(p.name for p in K8S.glob("*.yaml") if p.name != "kustomization.yaml")


def test_service_hpa_pdb_and_ingress_reach_the_deployment():
    deployment = one("Deployment", "stylestream")
    pod_labels = deployment["spec"]["template"]["metadata"]["labels"]
    assert selects(deployment["spec"]["selector"]["matchLabels"], pod_labels)
    assert deployment["spec"]["replicas"] == 2

    service = one("Service", "stylestream")
    assert selects(service["spec"]["selector"], pod_labels)
    [container] = deployment["spec"]["template"]["spec"]["containers"]
    ports = {p["name"]: p["containerPort"] for p in container["ports"]}
    [service_port] = service["spec"]["ports"]
    assert service_port["targetPort"] in ports

    hpa = one("HorizontalPodAutoscaler", "stylestream")
    assert hpa["spec"]["scaleTargetRef"] == {"apiVersion": "apps/v1", "kind": "Deployment", "name": "stylestream"}
    assert hpa["spec"]["minReplicas"] >= deployment["spec"]["replicas"]

    assert selects(one("PodDisruptionBudget", "stylestream")["spec"]["selector"]["matchLabels"], pod_labels)

    ingress = one("Ingress", "stylestream")
    backends = [p["backend"]["service"] for rule in ingress["spec"]["rules"] for p in rule["http"]["paths"]]
    assert backends and all(b["name"] == "stylestream" and b["port"]["name"] == service_port["name"] for b in backends)

    redis = one("Deployment", "stylestream-redis")
    assert selects(
        one("Service", "stylestream-redis")["spec"]["selector"], redis["spec"]["template"]["metadata"]["labels"]
    )
    policy = one("NetworkPolicy", "stylestream-redis")
    assert selects(policy["spec"]["podSelector"]["matchLabels"], redis["spec"]["template"]["metadata"]["labels"])
    assert selects(policy["spec"]["ingress"][0]["from"][0]["podSelector"]["matchLabels"], pod_labels)


def test_pods_run_the_image_as_built(monkeypatch):
    """Probes hit real routes on the port the server listens on, as the user the image runs as,
    and the pod outlives its own drain."""
    pod = one("Deployment", "stylestream")["spec"]["template"]["spec"]
    [container] = pod["containers"]
    ports = {p["name"]: p["containerPort"] for p in container["ports"]}
    config = one("ConfigMap", "stylestream")["data"]
    settings = settings_from_env(config, monkeypatch)
    assert list(ports.values()) == [settings.port] == [int(dockerfile("EXPOSE"))]

    routes = service_routes()
    probes = {kind: container[kind]["httpGet"] for kind in ("startupProbe", "livenessProbe", "readinessProbe")}
    assert probes["livenessProbe"]["path"] == "/healthz" and probes["readinessProbe"]["path"] == "/readyz"
    for probe in probes.values():
        assert probe["path"] in routes and probe["port"] in ports

    user, group = (int(x) for x in dockerfile("USER").split(":"))
    assert (pod["securityContext"]["runAsUser"], pod["securityContext"]["runAsGroup"]) == (user, group)
    assert pod["securityContext"]["runAsNonRoot"] and container["securityContext"]["readOnlyRootFilesystem"]
    assert "/var/lib/stylestream" in {m["mountPath"] for m in container["volumeMounts"]}  # the image's writable home

    [pause] = [int(x) for x in container["lifecycle"]["preStop"]["exec"]["command"][1:]]
    assert pod["terminationGracePeriodSeconds"] > pause + settings.drain_timeout_s
    assert container["resources"]["requests"]["cpu"] and container["resources"]["limits"]["memory"]


def test_session_store_and_ingress_settings_fit_the_server(monkeypatch):
    settings = settings_from_env(one("ConfigMap", "stylestream")["data"], monkeypatch)
    match = re.fullmatch(r"redis://([\w-]+):(\d+)/\d+", settings.session_store)
    assert match, settings.session_store
    redis_service = one("Service", "stylestream-redis")
    assert redis_service["metadata"]["name"] == match[1]
    assert [p["port"] for p in redis_service["spec"]["ports"]] == [int(match[2])]

    notes = one("Ingress", "stylestream")["metadata"]["annotations"]
    prefix = "nginx.ingress.kubernetes.io/"
    # the ingress must not cut a quiet stream before the server's own idle timeout does
    assert float(notes[prefix + "proxy-read-timeout"]) > settings.idle_timeout_s
    assert float(notes[prefix + "proxy-send-timeout"]) > settings.idle_timeout_s
    assert notes[prefix + "affinity"] == "cookie" and notes[prefix + "session-cookie-name"]
    assert nginx_size(notes[prefix + "proxy-body-size"]) >= settings.upload_max_bytes


# ---- the shared-styles overlay (docker/k8s/shared-styles) -------------------------------------


def strategic_merge(base, patch):
    """What kustomize's strategic-merge patch does with these patches: maps merge key by key;
    lists of named items (containers, volumes, volumeMounts) merge item by name; anything else
    the patch replaces."""
    if isinstance(base, dict) and isinstance(patch, dict):
        return {**base, **{k: strategic_merge(base[k], v) if k in base else v for k, v in patch.items()}}
    if (
        isinstance(base, list)
        and isinstance(patch, list)
        and all(isinstance(i, dict) and "name" in i for i in base + patch)
    ):
        merged = {item["name"]: item for item in base}
        for item in patch:
            merged[item["name"]] = strategic_merge(merged[item["name"]], item) if item["name"] in merged else item
        return list(merged.values())
    return patch


def overlay_manifests() -> list[dict]:
    """The overlay rendered as `kubectl apply -k docker/k8s/shared-styles` would: the base, its own
    resources, its patches applied to the base objects they name."""
    folder = K8S / "shared-styles"
    kustomization = yaml.safe_load((folder / "kustomization.yaml").read_text())
    assert kustomization["resources"][0] == ".."
    docs = manifests() + [
        d for name in kustomization["resources"][1:] for d in yaml.safe_load_all((folder / name).read_text()) if d
    ]
    for entry in kustomization["patches"]:
        patch = yaml.safe_load((folder / entry["path"]).read_text())
        [i] = [
            i
            for i, d in enumerate(docs)
            if (d["kind"], d["metadata"]["name"]) == (patch["kind"], patch["metadata"]["name"])
        ]
        docs[i] = strategic_merge(docs[i], patch)
    return docs


@pytest.mark.parametrize("version", K8S_VERSIONS)
def test_shared_styles_overlay_is_valid_against_the_kubernetes_schema(version):
    for doc in overlay_manifests():
        kubernetes_validate.validate(doc, version, strict=True)


def test_shared_styles_overlay_mounts_one_rwx_claim_over_every_pods_styles_folder(monkeypatch):
    docs = overlay_manifests()
    [claim] = [d for d in docs if d["kind"] == "PersistentVolumeClaim"]
    assert "ReadWriteMany" in claim["spec"]["accessModes"]  # every replica writes uploads to it
    [deployment] = [d for d in docs if d["kind"] == "Deployment" and d["metadata"]["name"] == "stylestream"]
    pod = deployment["spec"]["template"]["spec"]
    [container] = pod["containers"]
    volumes = {v["name"]: v for v in pod["volumes"]}
    mounts = {m["mountPath"]: m["name"] for m in container["volumeMounts"]}
    styles_dir = re.search(r"STYLESTREAM_STYLES_DIR=(\S+)", (DOCKER / "Dockerfile").read_text())[1]
    assert volumes[mounts[styles_dir]]["persistentVolumeClaim"]["claimName"] == claim["metadata"]["name"]
    assert "emptyDir" in volumes[mounts["/var/lib/stylestream"]]  # the base's home and probes are kept
    assert container["readinessProbe"]["httpGet"]["path"] == "/readyz"
    [config] = [d for d in docs if d["kind"] == "ConfigMap" and d["metadata"]["name"] == "stylestream"]
    settings = settings_from_env(config["data"], monkeypatch)
    assert settings.styles_refresh_s > 0 and settings.session_store.startswith("redis://")


def nginx_size(value: str) -> int:
    match = re.fullmatch(r"(\d+)([kKmMgG]?)", value)
    assert match, value
    return int(match[1]) * {"": 1, "k": 1024, "m": 1024**2, "g": 1024**3}[match[2].lower()]


# ---- compose, nginx, Prometheus ----------------------------------------------------------------


@pytest.fixture(scope="module")
def compose() -> dict:
    return yaml.safe_load((DOCKER / "compose.yaml").read_text())


def test_compose_runs_two_replicas_of_one_image_behind_nginx_with_redis_and_prometheus(compose, monkeypatch):
    services = compose["services"]
    assert set(services) == {*REPLICAS, "redis", "nginx", "prometheus"}
    assert all("healthcheck" in s for s in services.values())
    replicas = [services[name] for name in REPLICAS]
    assert replicas[0]["image"] == replicas[1]["image"] and "stylestream" in replicas[0]["image"]
    for replica in replicas:
        settings = settings_from_env(replica["environment"], monkeypatch)
        assert settings.session_store == "redis://redis:6379/0"
        assert replica["depends_on"]["redis"]["condition"] == "service_healthy"
        assert int(replica["stop_grace_period"].rstrip("s")) > settings.drain_timeout_s
        assert replica["stop_signal"] == "SIGTERM"
        assert replica["healthcheck"]["test"][-1] in service_routes()
        assert "ports" not in replica  # reached only through nginx (which it trusts for X-Forwarded-For)
        # one styles volume for both, rescanned: an upload through nginx is usable on either replica
        assert replica["volumes"] == ["styles:/var/lib/stylestream/styles"] and settings.styles_refresh_s > 0
    assert {name: services["nginx"]["depends_on"][name]["condition"] for name in REPLICAS} == dict.fromkeys(
        REPLICAS, "service_healthy"
    )
    mounts = {m.split(":")[1] for s in ("nginx", "prometheus") for m in services[s]["volumes"]}
    assert mounts == {"/etc/nginx/nginx.conf", "/etc/prometheus/prometheus.yml"}
    for service in ("nginx", "prometheus"):
        [volume] = services[service]["volumes"]
        assert (DOCKER / volume.split(":")[0]).is_file()


def test_nginx_proxies_websockets_to_both_replicas(compose, monkeypatch):
    conf = (DOCKER / "nginx.conf").read_text()
    [upstream] = re.findall(r"upstream stylestream \{(.*?)\}", conf, re.S)
    port = settings_from_env(compose["services"][REPLICAS[0]]["environment"], monkeypatch).port
    assert re.findall(r"server ([\w-]+):(\d+)", upstream) == [(name, str(port)) for name in REPLICAS]
    assert "proxy_http_version 1.1;" in conf
    assert "proxy_set_header Upgrade $http_upgrade;" in conf
    assert "proxy_set_header Connection $connection_upgrade;" in conf
    idle = settings_from_env(compose["services"][REPLICAS[0]]["environment"], monkeypatch).idle_timeout_s
    for directive in ("proxy_read_timeout", "proxy_send_timeout"):
        [value] = re.findall(rf"{directive} (\w+);", conf)
        assert nginx_seconds(value) > idle
    [published] = compose["services"]["nginx"]["ports"]
    assert re.search(rf"listen {published.rsplit(':', 1)[1]};", conf)


def _nginx() -> str:
    binary = shutil.which("nginx") or (Path("/usr/sbin/nginx").exists() and "/usr/sbin/nginx")
    if binary:
        return binary
    if shutil.which("apt-get") is None or os.geteuid() != 0:
        pytest.skip("nginx not installed and no root apt-get to install it (`make servers` installs it)")
    subprocess.run(
        "apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq nginx >/dev/null",
        shell=True,
        check=True,
        timeout=600,
    )
    return shutil.which("nginx") or "/usr/sbin/nginx"


def test_nginx_accepts_the_config(tmp_path):
    """`nginx -t`, with the compose service names (which resolve only on the compose network)
    pointed at loopback."""
    conf = (DOCKER / "nginx.conf").read_text()
    for name in REPLICAS:
        conf = conf.replace(f"server {name}:", "server 127.0.0.1:")
    (tmp_path / "nginx.conf").write_text(conf)
    done = subprocess.run(
        [_nginx(), "-t", "-p", str(tmp_path), "-e", "/dev/stderr", "-c", str(tmp_path / "nginx.conf")],
        capture_output=True,
        text=True,
        timeout=30,
    )
    assert done.returncode == 0, done.stderr
    assert "test is successful" in done.stderr


def test_prometheus_scrapes_metrics_of_both_replicas(compose, monkeypatch):
    config = yaml.safe_load((DOCKER / "prometheus.yml").read_text())
    [job] = [j for j in config["scrape_configs"] if j["job_name"] == "stylestream"]
    assert job["metrics_path"] in service_routes()
    port = settings_from_env(compose["services"][REPLICAS[0]]["environment"], monkeypatch).port
    assert [t for c in job["static_configs"] for t in c["targets"]] == [f"{name}:{port}" for name in REPLICAS]
    promtool = shutil.which("promtool")
    if promtool:  # the real checker where Prometheus is installed
        done = subprocess.run(
            [promtool, "check", "config", "--syntax-only", str(DOCKER / "prometheus.yml")],
            capture_output=True,
            text=True,
            timeout=60,
        )
        assert done.returncode == 0, done.stdout + done.stderr


def test_compose_file_passes_the_compose_cli(compose):
    """Only where a compose CLI is installed (none is fetched: it would need the network)."""
    for command in (["docker", "compose"], ["docker-compose"], ["podman-compose"]):
        if shutil.which(command[0]) and subprocess.run([*command, "version"], capture_output=True).returncode == 0:
            done = subprocess.run(
                [*command, "-f", str(DOCKER / "compose.yaml"), "config", "-q"],
                capture_output=True,
                text=True,
                timeout=60,
            )
            assert done.returncode == 0, done.stdout + done.stderr
            return
    pytest.skip("no compose CLI installed (docker compose, docker-compose or podman-compose)")


def test_forwarded_headers_are_trusted_from_the_proxy_alone(compose):
    """compose: the replicas take X-Forwarded-For from nginx's fixed address only, inside the
    network's subnet; k8s: only the ingress controller (and monitoring) can reach the pods, which
    is what makes trusting every sender safe there; nginx overwrites the header."""
    import ipaddress

    spec = compose
    trusted = [spec["services"][name]["environment"]["FORWARDED_ALLOW_IPS"] for name in REPLICAS]
    address = spec["services"]["nginx"]["networks"]["default"]["ipv4_address"]
    [subnet] = [c["subnet"] for c in spec["networks"]["default"]["ipam"]["config"]]
    assert trusted == [address, address] and ipaddress.ip_address(address) in ipaddress.ip_network(subnet)
    conf = (DOCKER / "nginx.conf").read_text()
    assert re.findall(r"proxy_set_header X-Forwarded-For (\S+);", conf) == ["$remote_addr"]
    policy = one("NetworkPolicy", "stylestream")
    pods = one("Deployment", "stylestream")["spec"]["template"]["metadata"]["labels"]
    assert selects(policy["spec"]["podSelector"]["matchLabels"], pods)
    sources = [s["namespaceSelector"]["matchLabels"] for s in policy["spec"]["ingress"][0]["from"]]
    assert {"kubernetes.io/metadata.name": "ingress-nginx"} in sources
    assert one("ConfigMap", "stylestream")["data"]["FORWARDED_ALLOW_IPS"] == "*"
