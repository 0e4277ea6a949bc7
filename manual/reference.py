"""The manual's reference pages, generated from the code at build time (``make docs``).

A page holds a marker comment, ``<!-- generated: NAME -->``, which :mod:`manual.hooks` replaces
by the Markdown that :data:`GENERATORS` makes for NAME:

- ``spec``: the problem spec's fields, from the JSON schema of :class:`fpm.model.spec.ProblemSpec`
  (the Pydantic models the library and the service validate with);
- ``openapi``: the REST API, from the app's own OpenAPI document (``/openapi.json``);
- ``fpmcal`` and ``fpm-client``: the command lines, from their argparse parsers;
- ``settings``: the service's environment variables, from :class:`service.settings.Settings`.

So the reference cannot drift from the code: change a field, an option or a route and the page
changes with it.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import os
from collections.abc import Callable
from typing import Any

MARKER = "<!-- generated: {} -->"


def _cell(text: Any) -> str:
    """Text fit for one Markdown table cell."""
    return " ".join(str(text).split()).replace("|", "\\|")


def _type(schema: dict[str, Any]) -> str:
    """A JSON schema's type in a few words: ``number``, ``array of LoadCase``, ``A or B``."""
    if "$ref" in schema:
        name = schema["$ref"].rsplit("/", 1)[-1]
        return f"[{name}](#{name.lower()})"
    for key in ("anyOf", "oneOf"):
        if key in schema:
            return " or ".join(dict.fromkeys(_type(s) for s in schema[key]))
    if "const" in schema:
        return f"`{json.dumps(schema['const'])}`"
    if "enum" in schema:
        return " or ".join(f"`{json.dumps(v)}`" for v in schema["enum"])
    kind = schema.get("type", "any")
    if kind == "array":
        if "prefixItems" in schema:
            return "[" + ", ".join(_type(s) for s in schema["prefixItems"]) + "]"
        return f"array of {_type(schema.get('items', {}))}"
    if kind == "object" and "additionalProperties" in schema:
        extra = schema["additionalProperties"]
        return f"object of {_type(extra) if isinstance(extra, dict) else 'any'}"
    return str(kind)


def _limits(schema: dict[str, Any]) -> str:
    words = {
        "minimum": ">=",
        "maximum": "<=",
        "exclusiveMinimum": ">",
        "exclusiveMaximum": "<",
        "minItems": "items >=",
        "maxItems": "items <=",
        "minLength": "length >=",
    }
    return ", ".join(f"{w} {schema[k]}" for k, w in words.items() if k in schema)


def _model_table(name: str, model: dict[str, Any]) -> list[str]:
    out = [f"### {name}", ""]
    if model.get("description"):
        out += [" ".join(model["description"].split()), ""]
    required = set(model.get("required", []))
    out += ["| field | type | default | limits | description |", "|---|---|---|---|---|"]
    for field, schema in model.get("properties", {}).items():
        default = (
            "*required*"
            if field in required
            else (f"`{json.dumps(schema['default'])}`" if "default" in schema else "")
        )
        out.append(
            f"| `{field}` | {_cell(_type(schema))} | {_cell(default)} | "
            f"{_cell(_limits(schema))} | {_cell(schema.get('description', ''))} |"
        )
    return out + [""]


def spec() -> str:
    """The problem spec's fields, model by model, from ProblemSpec's JSON schema."""
    from fpm.model.spec import ProblemSpec

    schema = ProblemSpec.model_json_schema()
    out = _model_table("ProblemSpec", schema)
    for name, model in sorted(schema.get("$defs", {}).items()):
        out += _model_table(name, model)
    return "\n".join(out)


def openapi() -> str:
    """The REST API: every operation of the app's OpenAPI document, with its parameters and
    answers."""
    from service.main import create_app

    document = create_app().openapi()
    out = [
        f"OpenAPI {document['openapi']}, *{document['info']['title']}* "
        f"version {document['info']['version']}. The running service serves the same document "
        "at `/openapi.json`, browsable at `/docs` (Swagger UI) and `/redoc`.",
        "",
    ]
    for path, operations in document["paths"].items():
        for method, op in operations.items():
            out += [f"### `{method.upper()} {path}`", ""]
            if op.get("summary"):
                out += [f"**{_cell(op['summary'])}** (`{op.get('operationId', '')}`)", ""]
            if op.get("description"):
                out += [op["description"].strip(), ""]
            params = op.get("parameters", [])
            if params:
                out += [
                    "| parameter | in | type | required | description |",
                    "|---|---|---|---|---|",
                ]
                for p in params:
                    out.append(
                        f"| `{p['name']}` | {p['in']} | {_cell(_type(p.get('schema', {})))} | "
                        f"{'yes' if p.get('required') else 'no'} | "
                        f"{_cell(p.get('description', ''))} |"
                    )
                out.append("")
            body = op.get("requestBody", {}).get("content", {})
            if body:
                kinds = ", ".join(f"`{k}`" for k in body)
                out += [f"Request body: {kinds}.", ""]
            answers = op.get("responses", {})
            if answers:
                out += ["| status | meaning |", "|---|---|"]
                for code, answer in answers.items():
                    out.append(f"| {code} | {_cell(answer.get('description', ''))} |")
                out.append("")
    schemas = document.get("components", {}).get("schemas", {})
    if schemas:
        out += ["## Schemas", ""]
        for name, model in sorted(schemas.items()):
            out += _model_table(name, model)
    return "\n".join(out)


class _Caught(Exception):
    def __init__(self, parser: argparse.ArgumentParser):
        self.parser = parser


def _parser_of(build: Callable[[], Any]) -> argparse.ArgumentParser:
    """The parser a CLI builds, caught as it starts to parse (no CLI code changes needed)."""
    original = argparse.ArgumentParser.parse_args

    def catch(self: argparse.ArgumentParser, *args: Any, **kwargs: Any) -> Any:
        raise _Caught(self)

    argparse.ArgumentParser.parse_args = catch  # type: ignore[method-assign]
    try:
        build()
    except _Caught as caught:
        return caught.parser
    finally:
        argparse.ArgumentParser.parse_args = original  # type: ignore[method-assign]
    raise RuntimeError("the command line did not build a parser")


def _helps(parser: argparse.ArgumentParser, level: int = 3) -> list[str]:
    out = [
        f"{'#' * level} `{parser.prog}`",
        "",
        "```text",
        parser.format_help().rstrip(),
        "```",
        "",
    ]
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for sub in dict.fromkeys(action.choices.values()):
                out += _helps(sub, level + 1 if level < 4 else level)
    return out


def _cli(build: Callable[[], Any]) -> str:
    old = os.environ.get("COLUMNS")
    os.environ["COLUMNS"] = "100"  # argparse wraps to the terminal: the same page everywhere
    try:
        with contextlib.redirect_stdout(io.StringIO()):
            parser = _parser_of(build)
        return "\n".join(_helps(parser))
    finally:
        if old is None:
            os.environ.pop("COLUMNS", None)
        else:
            os.environ["COLUMNS"] = old


def fpmcal() -> str:
    from fpmcal import cli

    return _cli(lambda: cli.main([]))


def fpm_client() -> str:
    from client import cli

    return _cli(lambda: cli.main([]))


def settings() -> str:
    """The service's settings: each field with its environment variable and default."""
    from service.settings import Settings

    schema = Settings.model_json_schema()
    prefix = Settings.model_config.get("env_prefix", "")
    out = ["| variable | type | default | description |", "|---|---|---|---|"]
    for field, info in Settings.model_fields.items():
        names = [field]
        alias = info.validation_alias
        if alias is not None:
            choices = getattr(alias, "choices", [alias])
            names = [c for c in choices if isinstance(c, str)] or names
        else:
            names = [prefix + field]
        prop = schema["properties"].get(field) or next(
            (schema["properties"][n] for n in names if n in schema["properties"]), {}
        )
        value = info.get_default(call_default_factory=True)
        default = "" if info.is_required() else f"`{json.dumps(value, default=str)}`"
        variables = " or ".join(f"`{n.upper()}`" for n in names)
        out.append(
            f"| {variables} | {_cell(_type(prop))} | {_cell(default)} | "
            f"{_cell(info.description or prop.get('description', ''))} |"
        )
    return "\n".join(out) + "\n"


GENERATORS: dict[str, Callable[[], str]] = {
    "spec": spec,
    "openapi": openapi,
    "fpmcal": fpmcal,
    "fpm-client": fpm_client,
    "settings": settings,
}


def expand(markdown: str) -> str:
    """``markdown`` with every generator's marker replaced by what it makes."""
    for name, make in GENERATORS.items():
        marker = MARKER.format(name)
        if marker in markdown:
            markdown = markdown.replace(marker, make())
    return markdown
