"""Static checks of the deployment files against the application they deploy.

The Kubernetes manifests (deploy/), docker-compose.yml, the Dockerfiles and the nginx config are
parsed and compared with the FastAPI app's real routes and OpenAPI description, its settings
(the `IFNET_*` variables it reads) and each other: probes must hit routes the app serves,
readiness must be the route that answers 503 before the model is ready, every env variable must be
one the service reads, the balancer must point at the replicas' service and port, and so on.
No Docker or cluster is needed.
"""

import ast
import asyncio
import importlib.util
import re
from pathlib import Path

import httpx
import pytest
import yaml

from service.app import create_app
from service.settings import Settings

ROOT = Path(__file__).resolve().parents[2]
DEPLOY = ROOT / "deploy"
COMPOSE = ROOT / "docker-compose.yml"
DOCKERFILE = ROOT / "Dockerfile"
NGINX_DOCKERFILE = ROOT / "docker" / "nginx.Dockerfile"
NGINX_CONF = ROOT / "docker" / "nginx.conf"
HEALTHCHECK = ROOT / "docker" / "healthcheck.py"
ENV_PREFIX = Settings.model_config["env_prefix"]


# ---------------------------------------------------------------- the app and its settings


@pytest.fixture(scope="module")
def app():
    return create_app(Settings())


@pytest.fixture(scope="module")
def openapi_paths(app) -> dict:
    return app.openapi()["paths"]


@pytest.fixture(scope="module")
def get_routes(openapi_paths) -> set[str]:
    """Paths the app answers with GET (probes use GET), as its OpenAPI description lists them."""
    return {path for path, operations in openapi_paths.items() if "get" in operations}


class NotLoaded:
    """GETs against the app before its lifespan has run: no model loaded, exactly as while a pod starts."""

    def __init__(self, app):
        self.app = app

    def get(self, path: str) -> httpx.Response:
        async def get() -> httpx.Response:
            transport = httpx.ASGITransport(app=self.app)  # runs no lifespan
            async with httpx.AsyncClient(transport=transport, base_url="http://testserver") as client:
                return await client.get(path)

        return asyncio.run(get())


@pytest.fixture(scope="module")
def not_loaded(app) -> NotLoaded:
    return NotLoaded(app)


def setting_variables() -> set[str]:
    return {f"{ENV_PREFIX}{name}".upper() for name in Settings.model_fields}


# ---------------------------------------------------------------- Kubernetes manifests


def manifests() -> dict[str, list[dict]]:
    found = {}
    for path in sorted(DEPLOY.glob("*.y*ml")):
        with path.open() as stream:
            found[path.name] = [doc for doc in yaml.safe_load_all(stream) if doc is not None]
    return found


def objects(kind: str) -> list[dict]:
    return [doc for docs in manifests().values() for doc in docs if doc.get("kind") == kind]


def the(kind: str) -> dict:
    found = objects(kind)
    assert len(found) == 1, f"expected one {kind} in deploy/, found {len(found)}"
    return found[0]


def containers() -> list[dict]:
    return the("Deployment")["spec"]["template"]["spec"]["containers"]


def cpu(quantity) -> float:
    text = str(quantity)
    return float(text[:-1]) / 1000 if text.endswith("m") else float(text)


def memory(quantity) -> float:
    units = {"Ki": 2**10, "Mi": 2**20, "Gi": 2**30, "K": 1e3, "M": 1e6, "G": 1e9}
    match = re.fullmatch(r"(\d+(?:\.\d+)?)([KMG]i?)?", str(quantity))
    assert match, f"unparsed memory quantity {quantity!r}"
    return float(match.group(1)) * units.get(match.group(2) or "", 1)


def test_every_manifest_parses_and_is_listed_in_the_kustomization():
    found = manifests()
    assert found, "no manifests in deploy/"
    kustomization = found.pop("kustomization.yaml")[0]
    for name, docs in found.items():
        assert docs, f"{name} is empty"
        for doc in docs:
            assert {"apiVersion", "kind", "metadata"} <= doc.keys(), f"{name}: {sorted(doc)}"
            assert doc["metadata"].get("name"), f"{name}: {doc['kind']} without a name"
    assert sorted(kustomization["resources"]) == sorted(found), "kustomization resources != the manifests"
    assert {obj["kind"] for docs in found.values() for obj in docs} >= {
        "Deployment",
        "Service",
        "HorizontalPodAutoscaler",
    }


@pytest.mark.parametrize("probe", ["startupProbe", "livenessProbe", "readinessProbe"])
def test_probes_hit_routes_the_app_serves(probe, get_routes):
    for container in containers():
        assert probe in container, f"container {container['name']} has no {probe}"
        http = container[probe]["httpGet"]
        assert http["path"] in get_routes, f"{probe} path {http['path']} is not a GET route: {sorted(get_routes)}"
        ports = {port.get("name") for port in container["ports"]} | {
            port["containerPort"] for port in container["ports"]
        }
        assert http["port"] in ports, f"{probe} port {http['port']} is not a container port"
        assert container[probe].get("timeoutSeconds", 1) < container[probe].get("periodSeconds", 10) + 1


def test_readiness_fails_and_liveness_passes_before_the_model_is_loaded(not_loaded):
    """Readiness must answer 503 until the model is loaded (no traffic to a warming-up pod); startup
    and liveness must answer 200 meanwhile (else the kubelet restarts a pod that is loading)."""
    for container in containers():
        ready = container["readinessProbe"]["httpGet"]["path"]
        assert not_loaded.get(ready).status_code == 503, f"readiness {ready} does not report a missing model"
        for probe in ("startupProbe", "livenessProbe"):
            path = container[probe]["httpGet"]["path"]
            assert path != ready
            assert not_loaded.get(path).status_code == 200, f"{probe} {path} fails while the model loads"


def test_container_port_is_the_service_port():
    exposed = re.search(r"^EXPOSE\s+(\d+)", DOCKERFILE.read_text(), re.MULTILINE)
    assert exposed, "Dockerfile has no EXPOSE"
    for container in containers():
        assert [port["containerPort"] for port in container["ports"]] == [int(exposed.group(1))]
        assert int(exposed.group(1)) == Settings.model_fields["port"].default


def test_resources_are_requested_and_limited():
    for container in containers():
        resources = container["resources"]
        for kind, parse in (("cpu", cpu), ("memory", memory)):
            request, limit = resources["requests"][kind], resources["limits"][kind]
            assert 0 < parse(request) <= parse(limit), f"{container['name']} {kind}: {request} / {limit}"


def test_env_variables_are_settings_the_service_reads():
    known = setting_variables()
    for container in containers():
        names = [item["name"] for item in container.get("env", [])]
        unknown = [name for name in names if name.startswith(ENV_PREFIX.upper()) and name not in known]
        assert not unknown, f"not service settings: {unknown}; known: {sorted(known)}"
        # One rule for the thread count, the service's own from the cgroup quota (rounded down), as
        # in the image; a downward-API value of limits.cpu would round a fractional limit up.
        assert f"{ENV_PREFIX.upper()}THREADS" not in names


def test_pods_run_unprivileged_as_the_image_user():
    user = re.search(r"^USER\s+(\d+)(?::(\d+))?", DOCKERFILE.read_text(), re.MULTILINE)
    assert user, "the Dockerfile's USER must be a numeric uid (runAsNonRoot needs one)"
    pod = the("Deployment")["spec"]["template"]["spec"]
    assert pod["securityContext"]["runAsNonRoot"] is True
    assert pod["securityContext"]["runAsUser"] == int(user.group(1)) != 0
    volumes = {volume["name"] for volume in pod.get("volumes", [])}
    for container in pod["containers"]:
        security = container["securityContext"]
        assert security["allowPrivilegeEscalation"] is False
        assert security["capabilities"]["drop"] == ["ALL"]
        if security.get("readOnlyRootFilesystem"):
            mounts = {mount["mountPath"]: mount["name"] for mount in container.get("volumeMounts", [])}
            assert mounts.get("/tmp") in volumes, "a read-only root filesystem needs a writable /tmp"


def test_graceful_shutdown_fits_the_termination_grace_period():
    pod = the("Deployment")["spec"]["template"]["spec"]
    for container in pod["containers"]:
        env = {item["name"]: item.get("value") for item in container.get("env", [])}
        drain = float(
            env.get(f"{ENV_PREFIX.upper()}SHUTDOWN_TIMEOUT_S") or Settings.model_fields["shutdown_timeout_s"].default
        )
        pre_stop = container.get("lifecycle", {}).get("preStop", {}).get("exec", {}).get("command", [])
        sleep = float(pre_stop[-1]) if pre_stop[:1] == ["sleep"] else 0.0
        assert sleep + drain < pod["terminationGracePeriodSeconds"]


def test_service_and_selectors_reach_the_pods():
    deployment = the("Deployment")
    labels = deployment["spec"]["template"]["metadata"]["labels"]
    assert deployment["spec"]["selector"]["matchLabels"].items() <= labels.items()
    service = the("Service")
    assert service["spec"]["selector"].items() <= labels.items()
    port_names = {port["name"] for container in containers() for port in container["ports"]}
    port_numbers = {port["containerPort"] for container in containers() for port in container["ports"]}
    for port in service["spec"]["ports"]:
        assert port["targetPort"] in port_names | port_numbers
    for budget in objects("PodDisruptionBudget"):
        assert budget["spec"]["selector"]["matchLabels"].items() <= labels.items()


def test_autoscaler_targets_the_deployment_on_cpu():
    hpa = the("HorizontalPodAutoscaler")
    assert hpa["apiVersion"] == "autoscaling/v2"
    deployment = the("Deployment")
    target = hpa["spec"]["scaleTargetRef"]
    assert (target["apiVersion"], target["kind"], target["name"]) == (
        deployment["apiVersion"],
        "Deployment",
        deployment["metadata"]["name"],
    )
    cpu_metrics = [
        metric["resource"]["target"]
        for metric in hpa["spec"]["metrics"]
        if metric["type"] == "Resource" and metric["resource"]["name"] == "cpu"
    ]
    assert cpu_metrics and cpu_metrics[0]["type"] == "Utilization" and 0 < cpu_metrics[0]["averageUtilization"] <= 100
    assert 1 < hpa["spec"]["minReplicas"] <= hpa["spec"]["maxReplicas"]
    # Utilization is relative to the request: every container needs a CPU request.
    assert all(cpu(container["resources"]["requests"]["cpu"]) > 0 for container in containers())
    for budget in objects("PodDisruptionBudget"):
        assert budget["spec"]["minAvailable"] < hpa["spec"]["minReplicas"], "the budget would block every drain"


# ---------------------------------------------------------------- docker-compose.yml


def compose() -> dict:
    return yaml.safe_load(COMPOSE.read_text())


def interpolate(value) -> str:
    """Compose's ${VAR:-default} with the defaults, as when no variable is set."""
    return re.sub(r"\$\{[A-Z0-9_]+(?::?-([^}]*))?\}", lambda m: m.group(1) or "", str(value))


def test_compose_services_are_limited_healthchecked_and_on_loopback():
    services = compose()["services"]
    assert {"ifnet", "ifnet-replica", "ifnet-lb"} <= services.keys()
    assert "version" not in compose(), "the obsolete `version` key makes compose v2 warn"
    for name, service in services.items():
        assert float(interpolate(service["cpus"])) > 0, name
        assert memory(interpolate(service["mem_limit"]).replace("m", "M").replace("g", "G")) > 0, name
        assert service["restart"] in ("always", "unless-stopped"), name
        for port in service.get("ports", []):
            assert interpolate(port).startswith("127.0.0.1:"), f"{name} publishes {port} beyond loopback"
    assert "ports" not in services["ifnet-replica"], "replicas are reached through the balancer only"
    assert services["ifnet-replica"]["profiles"] == services["ifnet-lb"]["profiles"] == ["scaleout"]
    assert "profiles" not in services["ifnet"]
    dependency = services["ifnet-lb"]["depends_on"]["ifnet-replica"]
    assert dependency["condition"] == "service_healthy"


def test_compose_env_variables_are_settings_the_service_reads():
    known = setting_variables()
    for name, service in compose()["services"].items():
        env = service.get("environment", [])
        names = [item.split("=")[0] for item in env] if isinstance(env, list) else list(env)
        unknown = [var for var in names if var not in known]
        assert not unknown, f"{name}: not service settings: {unknown}"
        assert f"{ENV_PREFIX.upper()}THREADS" not in names, "threads come from the CPU limit"


def test_healthchecks_hit_the_readiness_route(get_routes, not_loaded):
    spec = importlib.util.spec_from_file_location("healthcheck", HEALTHCHECK)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    assert module.READY_PATH in get_routes
    assert not_loaded.get(module.READY_PATH).status_code == 503, "Docker would report a loading service healthy"
    assert module.health_url({"IFNET_PORT": "9000"}) == f"http://127.0.0.1:9000{module.READY_PATH}"
    # The image and compose run that script, at the path the Dockerfile copies it to.
    copied = re.search(r"^COPY\s+docker/healthcheck\.py\s+(\S+)", DOCKERFILE.read_text(), re.MULTILINE)
    assert copied, "the Dockerfile does not copy docker/healthcheck.py"
    healthcheck = re.search(r"^HEALTHCHECK .*\n?.*CMD (\[.*\])", DOCKERFILE.read_text(), re.MULTILINE)
    assert healthcheck and copied.group(1) in healthcheck.group(1)
    for name in ("ifnet", "ifnet-replica"):
        assert copied.group(1) in compose()["services"][name]["healthcheck"]["test"]


# ---------------------------------------------------------------- Dockerfiles and nginx


def test_image_carries_every_model_module_the_service_imports():
    """The image copies `service/` whole but only the NumPy part of `model/`: it must be enough."""
    needed = set()
    for path in (ROOT / "service").glob("*.py"):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom) and node.module and node.module.split(".")[0] == "model":
                needed.add(node.module)
            elif isinstance(node, ast.Import):
                needed.update(alias.name for alias in node.names if alias.name.split(".")[0] == "model")
    dockerfile = DOCKERFILE.read_text()
    dockerignore = (ROOT / ".dockerignore").read_text().split()
    for module in sorted(needed):
        relative = module.replace(".", "/") + ".py"
        assert re.search(rf"^COPY\s+.*\b{re.escape(relative)}\b.*\s/opt/app/model/", dockerfile, re.MULTILINE), (
            f"the service imports {module} but the Dockerfile does not copy {relative}"
        )
        assert f"!{relative}" in dockerignore, f".dockerignore keeps {relative} out of the build context"
        init = str(Path(relative).parent / "__init__.py")
        assert init in dockerfile and f"!{init}" in dockerignore


def test_dockerfiles_build_on_bookworm_slim_without_torch():
    for path in (DOCKERFILE, NGINX_DOCKERFILE):
        text = path.read_text()
        assert re.search(r"^ARG BASE_IMAGE=debian:bookworm-slim$", text, re.MULTILINE), path.name
        assert not re.search(r"^#\s*syntax=", text, re.MULTILINE), f"{path.name}: the legacy builder is used"
        assert "--no-install-recommends" in text and "rm -rf /var/lib/apt/lists/*" in text
    text = DOCKERFILE.read_text()
    assert "['optional-dependencies']['serve']" in text, "the build installs the `serve` extra"
    assert not re.search(r"\b(train|dev)\b'?\]", text), "only the `serve` extra belongs in the image"
    stages = re.findall(r"^FROM\s+\S+(?:\s+AS\s+(\S+))?", text, re.MULTILINE)
    assert len(stages) == 2, f"expected a build and a runtime stage, found {stages}"
    runtime = text[text.rindex("\nFROM ") :]
    assert "docker/ca" not in runtime, "extra CA certificates belong to the build stage only"
    assert re.search(r"^HEALTHCHECK ", runtime, re.MULTILINE)


def test_nginx_balances_the_replica_service():
    conf = NGINX_CONF.read_text()
    services = compose()["services"]
    upstream = re.search(r"upstream\s+(\w+)\s*\{([^}]*)\}", conf)
    assert upstream, "no upstream block"
    servers = re.findall(r"^\s*server\s+([\w.-]+):(\d+)", upstream.group(2), re.MULTILINE)
    exposed = int(re.search(r"^EXPOSE\s+(\d+)", DOCKERFILE.read_text(), re.MULTILINE).group(1))
    assert servers == [("ifnet-replica", str(exposed))]
    assert f"proxy_pass http://{upstream.group(1)};" in conf
    listen = re.search(r"^\s*listen\s+(\d+);", conf, re.MULTILINE).group(1)
    assert [interpolate(port).rsplit(":", 1)[1] for port in services["ifnet-lb"]["ports"]] == [listen]
    lb_health = re.search(r"GET (/[\w-]+) HTTP", NGINX_DOCKERFILE.read_text())
    assert lb_health and f"location = {lb_health.group(1)} " in conf
    assert re.search(r"^USER\s+(?!root)\S+", NGINX_DOCKERFILE.read_text(), re.MULTILINE), "nginx runs as root"
