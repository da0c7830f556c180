"""Models named by an MLflow registry URI (``models:/<name>@<alias>`` or ``models:/<name>/<version>``).

The service does not import mlflow: it speaks the tracking server's REST API (stdlib ``urllib``):

1. ``GET /api/2.0/mlflow/registered-models/alias`` (or ``model-versions/get``) resolves the URI to a version;
2. ``GET /api/2.0/mlflow/model-versions/get-download-uri`` gives the version's artifact location;
3. the files ``MLmodel`` and ``model.onnx`` are read from there: through the server's artifact proxy
   (``mlflow-artifacts:/…`` locations, ``mlflow server`` with artifact serving, the default) or from disk
   (``file:`` or plain paths, a store on this machine or a shared volume).

The manifest travels inside ``MLmodel`` (``metadata.wearmocap_manifest``, written by ``training.i2s.pipeline`` when
it logs the model). The files land in ``<cache>/<name>/<version>/`` and are then loaded like a shipped model,
with the same sha256 and input/output checks.
"""

from __future__ import annotations

import json
import re
import shutil
import urllib.error
import urllib.parse
import urllib.request
from pathlib import Path

import yaml

from service.core.manifest import MLMODEL_METADATA_KEY, Manifest, write_manifest

_URI = re.compile(r"^models:/(?P<name>[^/@]+)(?:@(?P<alias>[^/@]+)|/(?P<version>\d+))$")


class RegistryError(RuntimeError):
    """A registry model could not be resolved or fetched; the message says which step failed."""


def parse_model_uri(uri: str) -> tuple[str, str | None, str | None]:
    """``models:/name@alias`` → (name, alias, None); ``models:/name/3`` → (name, None, "3")."""
    match = _URI.match(uri.strip())
    if not match:
        raise RegistryError(
            f"registry model URIs look like models:/<name>@<alias> or models:/<name>/<version>, got {uri!r}"
        )
    return match["name"], match["alias"], match["version"]


def _get_json(base: str, path: str, params: dict[str, str], timeout_s: float) -> dict:
    url = f"{base.rstrip('/')}{path}?{urllib.parse.urlencode(params)}"
    try:
        with urllib.request.urlopen(url, timeout=timeout_s) as response:
            return json.loads(response.read())
    except urllib.error.HTTPError as exc:
        raise RegistryError(f"GET {url}: HTTP {exc.code} {exc.read()[:200]!r}") from None
    except (urllib.error.URLError, TimeoutError) as exc:
        raise RegistryError(f"GET {url}: {exc}") from None


def _read_artifact(base: str, location: str, name: str, timeout_s: float) -> bytes:
    if location.startswith("mlflow-artifacts:"):
        path = urllib.parse.urlparse(location).path.lstrip("/")
        url = f"{base.rstrip('/')}/api/2.0/mlflow-artifacts/artifacts/{urllib.parse.quote(path)}/{name}"
        try:
            with urllib.request.urlopen(url, timeout=timeout_s) as response:
                return response.read()
        except urllib.error.HTTPError as exc:
            raise RegistryError(f"GET {url}: HTTP {exc.code}") from None
        except (urllib.error.URLError, TimeoutError) as exc:
            raise RegistryError(f"GET {url}: {exc}") from None
    parsed = urllib.parse.urlparse(location)
    if parsed.scheme in ("", "file"):
        path = Path(urllib.parse.unquote(parsed.path)) / name
        if not path.is_file():
            raise RegistryError(f"{path} does not exist (artifact location {location!r})")
        return path.read_bytes()
    raise RegistryError(
        f"artifact location {location!r}: the service reads mlflow-artifacts:/ (serve artifacts through the "
        "tracking server) or local paths, not {parsed.scheme}:"
    )


def fetch_registry_model(tracking_uri: str, model_uri: str, cache_dir: Path, timeout_s: float = 30.0) -> Path:
    """Resolve and download ``model_uri``; returns a directory with ``model.onnx`` and ``manifest.json``."""
    if not tracking_uri.startswith(("http://", "https://")):
        raise RegistryError(f"registry models need an http(s) MLflow tracking server URI, got {tracking_uri!r}")
    name, alias, version = parse_model_uri(model_uri)
    if alias is not None:
        found = _get_json(
            tracking_uri, "/api/2.0/mlflow/registered-models/alias", {"name": name, "alias": alias}, timeout_s
        )
    else:
        found = _get_json(
            tracking_uri, "/api/2.0/mlflow/model-versions/get", {"name": name, "version": version}, timeout_s
        )
    version = str(found["model_version"]["version"])
    location = _get_json(
        tracking_uri, "/api/2.0/mlflow/model-versions/get-download-uri", {"name": name, "version": version}, timeout_s
    )["artifact_uri"]
    mlmodel = yaml.safe_load(_read_artifact(tracking_uri, location, "MLmodel", timeout_s))
    raw_manifest = (mlmodel.get("metadata") or {}).get(MLMODEL_METADATA_KEY)
    if raw_manifest is None:
        raise RegistryError(f"{model_uri} (version {version}) has no {MLMODEL_METADATA_KEY} in its MLmodel metadata")
    manifest = Manifest.model_validate(raw_manifest)
    target = cache_dir / name / version
    if target.exists():
        shutil.rmtree(target)
    target.mkdir(parents=True)
    (target / "model.onnx").write_bytes(_read_artifact(tracking_uri, location, "model.onnx", timeout_s))
    write_manifest(manifest, target / "manifest.json")
    return target
