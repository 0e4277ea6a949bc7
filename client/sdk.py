"""The SDK: a small class over the service's HTTP API.

from client import Client
c = Client("http://127.0.0.1:8000")
done = c.calibrate("examples/paper-material-a.json", wait=True)
r = done["result"]
print(r["verdict"]["summary"])  # 'good', 'fair' or 'poor', on what basis, and why
print(r["stiffness"], r["d"], r["depth"])  # N/m per spring family, N s/m, layers
# The fit per load case: the relative discrepancy (%, scale-free) is the headline; the
# loaded-node error and the paper's unit (% of h) go beside it, never % of h alone.
for rel, loaded, h in zip(r["relative_discrepancy"], r["loaded_discrepancy"], r["discrepancy_h"]):
    print(f"{rel:.1f}% (loaded nodes {loaded:.1f}%, {h:.2f}% of h)")
# What a probe feels per load case: the model's work of the load over the reference's
# (1.0: the reference's stiffness; 1.5: 1.5 times too soft).
print(r["compliance_ratio"], r["validation_compliance_ratio"])
"""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any

import httpx

from .progress import ProgressBar, WaitLine

TERMINAL = ("succeeded", "failed", "canceled")
EXPORT_TIMEOUT = 600.0
"""Seconds :meth:`Client.export_bytes` waits by default for the service to make an export."""
SpecLike = dict[str, Any] | str | Path


class ApiError(Exception):
    """A problem+json answer: ``status``, ``title``, ``detail`` and the bad ``errors`` fields."""

    def __init__(self, status: int, title: str, detail: str, errors: list[dict] | None = None):
        super().__init__(f"{status} {title}: {detail}")
        self.status = status
        self.title = title
        self.detail = detail
        self.errors = errors or []


def retry_after(response: httpx.Response, default: float = 1.0) -> float:
    """The answer's Retry-After in seconds (the delay form; ``default`` when absent or a
    date), kept within 0.1-30 s."""
    try:
        seconds = float(response.headers.get("retry-after", default))
    except ValueError:
        seconds = default
    return min(max(seconds, 0.1), 30.0)


def read_spec(spec: SpecLike) -> dict[str, Any]:
    """A spec dict from a dict, a JSON file path, or a JSON string."""
    if isinstance(spec, dict):
        return spec
    text = str(spec)
    if not text.lstrip().startswith("{"):
        text = Path(text).read_text()
    return json.loads(text)


def spec_from_mesh(
    mesh: str | Path,
    *,
    fix: list[str],
    forces: list[str],
    youngs_modulus: float,
    poisson_ratio: float,
    density: float = 1000.0,
    spacing: float | None = None,
    **options: Any,
) -> dict[str, Any]:
    """A problem spec (a dict, ready for :meth:`Client.calibrate`) from a mesh file meshio reads
    (Gmsh .msh, VTK .vtu/.vtk, Abaqus .inp, STL, ...): hexahedra as they are, tetrahedra and
    closed triangle surfaces voxelised at ``spacing`` (m). The same as ``fpmcal spec from-mesh``.

    ``fix``: fixed nodes as short selectors (``"face:z-"``, ``"box:x0,y0,z0:x1,y1,z1"``,
    ``"nearest:x,y,z"``, ...); ``forces``: one load case each, ``"SELECTOR:fx,fy,fz"`` (N; append
    ``":distribute"`` to share the vector over the selected nodes; ``;`` between forces of one
    load case). ``options``: ``validation`` (one validation case per string, in the forces'
    form: loads the fit never sees, reported beside it), ``nodes`` (instead of ``spacing``:
    about how many lattice nodes, the spacing found for it), ``connectivity``, ``scale``
    (e.g. 0.001 for a mesh in mm),
    ``voxelise``, ``name``, ``dt`` (s, or "auto"), ``lattice`` (a tetrahedral mesh:
    ``"conforming"``, the default, the voxel lattice's surface nodes moved onto its surface; or
    ``"voxels"``), ``stiffness`` (``fpm.stiffness``; by default ``"field"`` for a tetrahedral
    organ loaded in two force patterns or more), ``loads`` (``fpm.loads``; by default ``"hat"``
    where the reference is the mesh's tetrahedra); see :func:`fpm.io.meshes.spec_from_mesh`.
    Raises :class:`fpm.io.meshes.MeshError` (e.g. an open surface) or ValueError (a bad selector).
    """
    from fpm.io.meshes import spec_from_mesh as build

    spec, _ = build(
        mesh,
        fix=fix,
        forces=forces,
        youngs_modulus=youngs_modulus,
        poisson_ratio=poisson_ratio,
        density=density,
        spacing=spacing,
        **options,
    )
    return spec


class Client:
    """Client of the calibration service.

    Args:
        base_url: e.g. ``http://127.0.0.1:8000``.
        api_key: sent as X-API-Key when the service requires one.
        timeout: per-request timeout, s.
        http: an httpx.Client to send through instead (e.g. FastAPI's TestClient).
    """

    def __init__(
        self,
        base_url: str,
        api_key: str | None = None,
        timeout: float = 30.0,
        http: httpx.Client | None = None,
    ):
        headers = {"X-API-Key": api_key} if api_key else {}
        if http is None:
            http = httpx.Client(base_url=base_url.rstrip("/"), timeout=timeout)
        http.headers.update(headers)
        self.http = http

    def close(self) -> None:
        self.http.close()

    def __enter__(self) -> Client:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _call(self, method: str, path: str, **kwargs: Any) -> Any:
        return self._request(method, path, **kwargs).json()

    def _request(self, method: str, path: str, **kwargs: Any) -> httpx.Response:
        response = self.http.request(method, path, **kwargs)
        if response.status_code >= 400:
            try:
                body = response.json()
            except ValueError:
                body = {"title": response.reason_phrase, "detail": response.text[:200]}
            raise ApiError(
                response.status_code,
                body.get("title", ""),
                body.get("detail", ""),
                body.get("errors"),
            )
        return response

    def calibrate(self, spec: SpecLike, wait: bool = False, progress: bool = True) -> dict:
        """Submit a calibration; with ``wait`` return it once finished (see :meth:`wait`).

        The spec's ``annealing.method`` picks the method: "two-stage" (the default: the
        stiffness annealed on static equilibria, then the fastest-settling d) or "paper".
        """
        calibration = self._call("POST", "/v1/calibrations", json=read_spec(spec))
        return self.wait(calibration["id"], progress=progress) if wait else calibration

    def get(self, calibration_id: str) -> dict:
        """A calibration: status, progress, result once succeeded.

        ``progress``: ``phase`` (queued, fem, annealing, damping, finalize, done), ``stage``
        (in words; the two-stage method's annealing is its stiffness search), ``stages``, the
        annealing's moves, temperature and best cost per chain, and ``damping`` (the damping
        stage's step and the d values tried). ``result``: ``method``, ``stiffness`` (k per
        spring family; ``k`` is the axis family's), ``d``, ``d_min``, ``depth``, per load case
        ``relative_discrepancy`` (%, the headline), ``loaded_discrepancy`` (%) and
        ``discrepancy_h`` (% of h), ``compliance_ratio`` (the load compliance ratio: 1.0 feels
        the reference's stiffness), ``settle_steps``, ``seconds`` per stage, ``warnings``, and
        ``verdict``: ``grade`` ('good', 'fair' or 'poor': a poor fit still succeeds),
        ``basis`` ('unseen' or 'fitted'), ``worst`` (%), ``floor`` (what the model family
        reaches, with its page), ``bounds`` (parameters at a bound), ``causes`` (each with an
        ``action``) and ``summary`` (one line).
        """
        return self._call("GET", f"/v1/calibrations/{calibration_id}")

    def calibrations(self, status: str | None = None, offset: int = 0, limit: int = 50) -> dict:
        """A page of calibrations, newest first: {items, total, offset, limit}."""
        params: dict[str, Any] = {"offset": offset, "limit": limit}
        if status:
            params["status"] = status
        return self._call("GET", "/v1/calibrations", params=params)

    def wait(
        self,
        calibration_id: str,
        *,
        poll: float = 0.5,
        timeout: float | None = None,
        progress: bool = True,
    ) -> dict:
        """Poll until the calibration is succeeded, failed or canceled; return it.

        ``progress`` draws a text bar on stderr. Raises TimeoutError after ``timeout`` s.
        """
        bar = ProgressBar() if progress else None
        deadline = None if timeout is None else time.monotonic() + timeout
        while True:
            calibration = self.get(calibration_id)
            if bar is not None:
                bar.update(calibration)
            if calibration["status"] in TERMINAL:
                if bar is not None:
                    bar.close()
                return calibration
            if deadline is not None and time.monotonic() > deadline:
                raise TimeoutError(f"calibration {calibration_id} still {calibration['status']}")
            time.sleep(poll)

    def cancel(self, calibration_id: str) -> dict:
        """Cancel a calibration; returns it (status canceled)."""
        return self._call("DELETE", f"/v1/calibrations/{calibration_id}")

    def parameter_sets(self, **filters: Any) -> list[dict]:
        """Stored parameter sets, newest first: stiffness per family, d (with the dt it was
        fitted at), depth, the discrepancies per load case, geometry (type, nodes, h),
        material and provenance.

        Filters: youngs_modulus, poisson_ratio, density (equal to 1e-6 relative),
        connectivity, name (substring).
        """
        params = {k: v for k, v in filters.items() if v is not None}
        return self._call("GET", "/v1/parameter-sets", params=params)["items"]

    def parameter_set(self, parameter_set_id: str) -> dict:
        """One stored parameter set."""
        return self._call("GET", f"/v1/parameter-sets/{parameter_set_id}")

    def export(
        self,
        parameter_set_id: str,
        format: str = "json",
        path: str | Path | None = None,
        *,
        timeout: float | None = EXPORT_TIMEOUT,
        progress: bool = True,
    ) -> Any:
        """A stored parameter set with its lattice, for other engines.

        ``format``: ``json`` (returned as a dict: nodes, springs ``[i, j, rest length,
        stiffness]``, masses, fixed nodes, d, dt, depth, perturbed layers per load case, units),
        ``vtu`` (ParaView: FPM and FEM displacements and their error per load case), ``sofa``
        (a SOFA XML scene, springs only) or ``sofa-python`` (a SofaPython3 scene with the volume
        term as a Python ForceField), all three returned as text. With ``path`` the answer is
        written there and the path returned. Waits while the service makes it
        (:meth:`export_bytes`).
        """
        body = self.export_bytes(parameter_set_id, format, timeout=timeout, progress=progress)
        if path is not None:
            Path(path).write_bytes(body)
            return Path(path)
        return json.loads(body) if format == "json" else body.decode()

    def export_bytes(
        self,
        parameter_set_id: str,
        format: str = "json",
        *,
        timeout: float | None = EXPORT_TIMEOUT,
        progress: bool = True,
    ) -> bytes:
        """The export of :meth:`export` as the service sends it (UTF-8 bytes).

        A worker makes an export the first time it is asked for (then the service keeps it a
        day): until it is made the service answers 202 (pending) and this asks again after
        the answer's Retry-After. ``progress`` shows the wait on one line of stderr. Raises
        TimeoutError after ``timeout`` s (None: no limit), and ApiError for an error answer
        (503 when the export job failed: Retry-After says when the service tries again).
        """
        url = f"/v1/parameter-sets/{parameter_set_id}/export"
        started = time.monotonic()
        line = None
        while True:
            response = self._request("GET", url, params={"format": format})
            waited = time.monotonic() - started
            if response.status_code != 202:
                if line is not None:
                    line.close(waited)
                return response.content
            if timeout is not None and waited >= timeout:
                if line is not None:
                    line.close(waited, done=False)
                raise TimeoutError(
                    f"the export of {parameter_set_id} as {format} is still being made after "
                    f"{waited:.0f} s"
                )
            if progress:
                if line is None:
                    line = WaitLine(f"{parameter_set_id} {format}: the service makes the export")
                line.update(waited)
            pause = retry_after(response)
            if timeout is not None:
                pause = min(pause, max(timeout - waited, 0.0))
            time.sleep(pause)

    def fem_reference(
        self, spec: SpecLike, *, poll: float = 0.5, timeout: float | None = None
    ) -> dict:
        """The FEM reference of ``spec`` (computed if not stored): nodes, displacements."""
        reference = self._call("POST", "/v1/fem-references", json=read_spec(spec))
        deadline = None if timeout is None else time.monotonic() + timeout
        while reference["status"] in ("queued", "running"):
            if deadline is not None and time.monotonic() > deadline:
                raise TimeoutError(f"FEM reference {reference['id']} still {reference['status']}")
            time.sleep(poll)
            reference = self._call("GET", f"/v1/fem-references/{reference['id']}")
        return reference

    def upload_mesh(self, mesh: dict[str, Any] | SpecLike) -> str:
        """Upload a tetrahedral mesh for the FEM reference; returns its id, to put in a spec's
        ``reference.mesh_id`` (the reference is then solved on the mesh with 10-node
        tetrahedra and read at the lattice nodes).

        ``mesh``: ``{"nodes": [[x, y, z], ...], "tetrahedra": [[i, j, k, l], ...]}`` (m,
        0-based), a JSON file or string of it, or a spec with ``reference.mesh`` (what
        ``fpmcal spec from-mesh`` writes), whose mesh is uploaded. Uploading the same mesh
        again returns the same id. Raises :class:`ApiError` (422 naming the element) for
        an inverted or degenerate tetrahedron.
        """
        data = read_spec(mesh)
        if "tetrahedra" not in data and "reference" in data:
            data = data["reference"]["mesh"]
        return str(self._call("POST", "/v1/meshes", json=data)["id"])

    def with_uploaded_mesh(self, spec: SpecLike) -> dict[str, Any]:
        """``spec`` with its ``reference.mesh`` uploaded and replaced by ``reference.mesh_id``
        (a small spec to submit; the same reference)."""
        data = json.loads(json.dumps(read_spec(spec)))
        mesh = (data.get("reference") or {}).pop("mesh", None)
        if mesh is not None:
            data["reference"]["mesh_id"] = self.upload_mesh(mesh)
        return data

    def health(self) -> dict:
        """Redis, workers, queue depth."""
        return self._call("GET", "/v1/health")
