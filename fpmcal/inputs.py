"""What the commands read and write: the spec file and the problem it makes, JSON in and out,
notes and warnings on stderr, and the errors a bad input raises."""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Any


class SpecFileError(Exception):
    """The SPEC argument is not a readable JSON file (exit status 2)."""


class ServiceError(RuntimeError):
    """The service did not answer what was asked (exit status 1)."""


def _read_spec(path: str) -> Any:
    """The parsed JSON of the spec file ``path``; :class:`SpecFileError` if there is none."""
    not_json = f"SPEC must be a JSON problem spec (got {path}, not JSON: "
    try:
        text = Path(path).read_text(encoding="utf-8")
    except FileNotFoundError:
        raise SpecFileError(
            f"SPEC {path}: no such file (give the path of a JSON problem spec, e.g. "
            "examples/small-box.json)"
        ) from None
    except IsADirectoryError:
        raise SpecFileError(f"SPEC {path} is a directory: give a JSON problem spec file") from None
    except UnicodeDecodeError:
        raise SpecFileError(not_json + "not UTF-8 text)" + _mesh_hint(path)) from None
    except OSError as e:
        raise SpecFileError(f"cannot read SPEC {path}: {e.strerror}") from None
    try:
        return json.loads(text)
    except json.JSONDecodeError as e:
        raise SpecFileError(not_json + f"{e})" + _mesh_hint(path)) from None


def _mesh_hint(path: str) -> str:
    """For a mesh file given as SPEC: how to make a spec of it."""
    from fpm.io.meshes import mesh_suffix

    if mesh_suffix(path) is None:
        return ""
    return (
        f"; {path} looks like a mesh: make a spec of it first with fpmcal spec from-mesh "
        f"{path} --spacing H --fix face:z- --force 'nearest:X,Y,Z:FX,FY,FZ' --E PA --nu NU"
    )


def _load(path: str, reference: str | None = None) -> Any:
    """The problem of the spec file ``path``; its notes go to stderr. ``reference``: a file
    whose displacement field becomes the spec's ``reference.displacements``
    (:func:`fpm.io.meshes.read_reference`). The service's size limits apply before it is built
    (:func:`fpm.limits.check_size`, then the memory a calibration of it needs:
    :func:`worker.memory.check`)."""
    from fpm.limits import check_size
    from fpm.model.problem import load_problem
    from fpm.model.spec import ProblemSpec
    from worker import memory

    spec = _read_spec(path)
    if reference is not None:
        from fpm.io.meshes import read_reference

        try:
            field = read_reference(reference, len(spec.get("load_cases") or []))
        except (OSError, ValueError) as e:
            raise SpecFileError(f"--reference {reference}: {e}") from None
        spec["reference"] = {**(spec.get("reference") or {}), "displacements": field}
    spec = ProblemSpec.model_validate(spec)
    memory.check(check_size(spec), machine=True)
    problem = load_problem(spec)
    for note in problem.notes:
        print(f"note: {note}", file=sys.stderr)
    return problem


def _warn(messages: list[str]) -> None:
    for message in messages:
        print(f"warning: {_one_line(message)}", file=sys.stderr)


def _one_line(message: object) -> str:
    return " ".join(str(message).split())


def _emit(data: dict[str, Any], out: str | None) -> None:
    text = json.dumps(data)
    if out:
        Path(out).write_text(text)
        print(f"wrote {out}", file=sys.stderr)
    else:
        print(text)


def _positive(text: str, flag: str) -> float:
    try:
        value = float(text)
    except ValueError:
        value = float("nan")
    if not value > 0 or value == float("inf"):
        raise ValueError(f"{flag} must be a number > 0 or 'auto' (got {text!r})")
    return value


def _read_json(path: str, what: str) -> Any:
    try:
        data = json.loads(Path(path).read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise SpecFileError(f"{what} {path}: not a readable JSON file ({_one_line(e)})") from None
    if not isinstance(data, dict):
        raise SpecFileError(f"{what} {path}: expected a JSON object")
    return data
