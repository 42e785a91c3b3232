"""Reading a site file: YAML (with duplicate keys caught) into a site model, and every mistake
into one line: ``file: key.path: problem`` (``file:LINE: ...`` where the line is known: YAML
syntax errors and duplicate keys).

`load_config` / `parse_config` give the contract's `SiteConfig` (what a node reads);
`load_site` / `parse_site` take the model, so the hub's loader (`fleetdaq.hub.config.load`)
validates its own, fuller schema with the same messages."""

from __future__ import annotations

import difflib
import re
from collections.abc import Mapping
from pathlib import Path
from types import UnionType
from typing import Annotated, Literal, TypeVar, Union, get_args, get_origin

import yaml
from pydantic import BaseModel, ValidationError
from pydantic_core import ErrorDetails

from fleetdaq.contract.config.site import SiteConfig
from fleetdaq.contract.drivers import DriverKind, driver_registry
from fleetdaq.contract.errors import ConfigError
from fleetdaq.contract.schema import CHANNEL_NAME

Site = TypeVar("Site", bound=SiteConfig)
_KEY_PATH = re.compile(r"^([a-z_]+(?:\.[A-Za-z0-9_/-]+|\[\d+\])*): (.*)$", re.S)


class _UniqueKeyLoader(yaml.SafeLoader):
    """A SafeLoader for site files; `_duplicate_keys` runs on its node graph before construction.

    PyYAML silently keeps the last of two equal keys: two nodes named ``wec`` would quietly
    become one. The check works on the composed nodes so that it knows the key path and the
    lines of both keys; a merge (``<<: *base``) followed by an override is not a duplicate.
    """


_MERGE_TAG = "tag:yaml.org,2002:merge"


def _duplicate_keys(root: yaml.Node) -> list[tuple[int, int, tuple[str | int, ...]]]:
    """Every repeated key as (line, first line, key path), in document order."""
    found: list[tuple[int, int, tuple[str | int, ...]]] = []
    visited: set[int] = set()  # aliases may share (or even contain) nodes
    stack: list[tuple[yaml.Node, tuple[str | int, ...]]] = [(root, ())]
    while stack:
        node, path = stack.pop()
        if id(node) in visited:
            continue
        visited.add(id(node))
        children: list[tuple[yaml.Node, tuple[str | int, ...]]] = []
        if isinstance(node, yaml.MappingNode):
            first: dict[tuple[str, str], int] = {}
            for key_node, value_node in node.value:
                if not isinstance(key_node, yaml.ScalarNode) or key_node.tag == _MERGE_TAG:
                    children.append((value_node, path))
                    continue
                ident = (str(key_node.tag), str(key_node.value))
                line = key_node.start_mark.line + 1
                if ident in first:
                    found.append((line, first[ident], (*path, str(key_node.value))))
                else:
                    first[ident] = line
                children.append((value_node, (*path, str(key_node.value))))
        elif isinstance(node, yaml.SequenceNode):
            children = [(item, (*path, i)) for i, item in enumerate(node.value)]
        stack.extend(reversed(children))
    return sorted(found)


def _load_yaml(text: str, source: str) -> object:
    loader = _UniqueKeyLoader(text)
    try:
        root = loader.get_single_node()
        if root is None:
            return None
        duplicates = _duplicate_keys(root)
        if duplicates:
            line, first, path = duplicates[0]
            parent = path[:-1]
            what = "key"
            if parent == ("nodes",):
                what = "node name"
            elif len(parent) == 3 and parent[0] == "nodes" and parent[2] == "streams":
                what = "stream name"
            more = f" (+{len(duplicates) - 1} more)" if len(duplicates) > 1 else ""
            raise ConfigError(
                f"{source}:{line}: {_path(path)}: duplicate {what} {path[-1]!r}"
                f" (first on line {first}){more}"
            )
        return loader.construct_document(root)
    finally:
        loader.dispose()


def _path(parts: tuple[str | int, ...] | list[str | int]) -> str:
    out: list[str] = []
    for item in parts:
        if isinstance(item, int):
            out.append(f"[{item}]")
        else:
            out.append(("." if out else "") + item)
    return "".join(out) or "(top level)"


def _user_loc(loc: tuple[int | str, ...], schema: type[SiteConfig]) -> tuple[int | str, ...]:
    """Pydantic's error location as the user wrote it: without union tags and `[key]`."""
    out: list[int | str] = []
    for i, item in enumerate(loc):
        if item == "[key]":
            continue  # the error is about a mapping key itself; the path already ends with it
        if schema.union_tag_at(loc, i):
            continue  # pydantic puts the union tag in the path; the user never wrote it
        out.append(item)
    return tuple(out)


def _tagged(model: type[BaseModel], tag: str) -> bool:
    """Whether `tag` picks `model` in a union: its `driver:` Literal, or a field of that name."""
    driver = model.model_fields.get("driver")
    if driver is not None and get_origin(driver.annotation) is Literal:
        return tag in get_args(driver.annotation)
    return tag in model.model_fields


def _model_at(loc: tuple[int | str, ...], schema: type[SiteConfig]) -> type[BaseModel] | None:
    """The model validating the mapping at pydantic location `loc` (for "did you mean"): found by
    following field annotations down from the site model, mapping keys (node and stream names)
    skipped, a union's member picked by its tag."""
    model: type[BaseModel] | None = schema
    i = 0
    while i < len(loc) and model is not None:
        key = loc[i]
        i += 1
        if isinstance(key, int):
            continue
        field = model.model_fields.get(key)
        if field is None:
            return None
        annotation = field.annotation
        if get_origin(_strip(annotation)) is dict:
            i += 1  # the mapping's own key (a node or stream name)
            annotation = get_args(_strip(annotation))[1]
        candidates = _models_in(annotation)
        if len(candidates) > 1:  # a discriminated union: pydantic puts the tag next
            tag = str(loc[i]) if i < len(loc) else ""
            picked = [m for m in candidates if _tagged(m, tag)]
            model = picked[0] if picked else None
            i += 1
        else:
            model = candidates[0] if candidates else None
    return model


def _strip(annotation: object) -> object:
    """`X | None` and `Annotated[X, ...]` -> X."""
    while True:
        if get_origin(annotation) is Annotated:
            annotation = get_args(annotation)[0]
            continue
        args = [a for a in get_args(annotation) if a is not type(None)]
        if get_origin(annotation) in (Union, UnionType) and len(args) == 1:
            annotation = args[0]
            continue
        return annotation


def _models_in(annotation: object) -> list[type[BaseModel]]:
    """The model classes inside an annotation (`X | None`, `list[X]`, `Annotated`, unions)."""
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return [annotation]
    out: list[type[BaseModel]] = []
    for arg in get_args(annotation):
        out += [m for m in _models_in(arg) if m not in out]
    return out


def _short(value: object) -> str:
    if value is None:
        return "null"
    if isinstance(value, bool):
        return str(value).lower()
    if isinstance(value, dict):
        return "a mapping"
    if isinstance(value, list):
        return "a list"
    text = repr(value)
    return text if len(text) <= 40 else text[:37] + "..."


def _unknown_key(loc: tuple[int | str, ...], schema: type[SiteConfig]) -> str:
    model = _model_at(loc[:-1], schema)
    if model is None:
        return "unknown key"
    allowed = list(model.model_fields)
    close = difflib.get_close_matches(str(loc[-1]), allowed, n=1)
    if close:
        return f"unknown key (did you mean {close[0]!r}?)"
    return f"unknown key (allowed: {', '.join(allowed)})"


def _bad_name(loc: tuple[int | str, ...], name: object, pattern: object) -> str:
    what = "name"
    if loc and loc[-1] == "[key]" and len(loc) >= 3:
        what = {
            "nodes": "node name",
            "streams": "stream name",
            "outputs": "output name",
            "interlocks": "interlock name",
        }.get(str(loc[-3]), "name")
    elif loc == ("site",):
        what = "site name"
    elif loc and loc[-1] == "name":
        what = "channel name"
    rule = (
        "letters, digits, '_', '.' or '-', starting with a letter, at most 63"
        if pattern == CHANNEL_NAME
        else "lower-case letters, digits, '_' or '-', starting with a letter, at most 63"
    )
    return f"invalid {what} {name!r} (use {rule})"


def _limit(kind: str, ctx: Mapping[str, object], got: str) -> str | None:
    """Bounds and lengths, said plainly: "must be greater than 0 (got -100)"."""
    bounds = {
        "greater_than": ("must be greater than", "gt"),
        "greater_than_equal": ("must be at least", "ge"),
        "less_than": ("must be less than", "lt"),
        "less_than_equal": ("must be at most", "le"),
    }
    if kind in bounds:
        words, key = bounds[kind]
        return f"{words} {ctx.get(key)} (got {got})"
    if kind == "too_short":
        if ctx.get("actual_length") == 0:
            return "must not be empty"
        return f"must have at least {ctx.get('min_length')} items (got {ctx.get('actual_length')})"
    if kind == "too_long":
        return f"must have at most {ctx.get('max_length')} items (got {ctx.get('actual_length')})"
    return None


def _driver_problem(kind: str, loc: tuple[int | str, ...], ctx: Mapping[str, object]) -> str | None:
    """Why a driver a site names is not there, when its plugin was refused (failed to load, ...)."""
    registry = driver_registry()
    if kind == "union_tag_invalid":
        return registry.problem(str(ctx.get("tag")))
    if kind == "literal_error" and loc and loc[-1] == "driver":
        return registry.problem(str(ctx.get("input", "")))
    return None


def _describe(err: ErrorDetails, schema: type[SiteConfig]) -> str:
    kind = str(err["type"])
    loc: tuple[int | str, ...] = tuple(err["loc"])
    ctx: Mapping[str, object] = err.get("ctx") or {}
    got = _short(err.get("input"))
    refused = _driver_problem(kind, loc, {**ctx, "input": err.get("input")})
    if refused is not None:
        return refused
    section = loc[2] if len(loc) > 2 else "streams"
    names = driver_registry().of_kind(
        DriverKind.OUTPUT if section == "outputs" else DriverKind.STREAM
    )
    fixed = {
        "missing": "required key is missing",
        "union_tag_invalid": (
            f"unknown driver {ctx.get('tag')!r} (expected one of {', '.join(names)})"
        ),
        "union_tag_not_found": f"missing 'driver' (one of {', '.join(names)})",
        "dict_type": f"expected a mapping of keys, got {got}",
        "model_type": f"expected a mapping of keys, got {got}",
        "model_attributes_type": f"expected a mapping of keys, got {got}",
        "list_type": f"expected a list, got {got}",
    }
    if kind in fixed:
        return fixed[kind]
    limit = _limit(kind, ctx, got)
    if limit is not None:
        return limit
    if kind == "extra_forbidden":
        return _unknown_key(loc, schema)
    if kind == "string_pattern_mismatch":
        return _bad_name(loc, err.get("input"), ctx.get("pattern"))
    msg = str(err["msg"]).removeprefix("Value error, ")
    if kind.endswith(("_type", "_parsing")) or kind == "finite_number":
        msg = f"{msg} (got {got})"
    return msg


def _one_line(text: str) -> str:
    return " ".join(part.strip() for part in text.splitlines() if part.strip())


def parse_config(text: str, source: str) -> SiteConfig:
    """Validate the text of a site file as a node reads it. `source` names it in errors."""
    return parse_site(text, source, SiteConfig)


def parse_site(text: str, source: str, schema: type[Site]) -> Site:
    """Validate the text of a site file against `schema` (the contract's `SiteConfig` or a
    subclass). `source` names it in errors. Raises ConfigError with one line."""
    try:
        raw = _load_yaml(text, source)
    except yaml.YAMLError as err:
        mark = getattr(err, "problem_mark", None)
        where = f":{mark.line + 1}" if mark is not None else ""
        problem = getattr(err, "problem", None) or str(err)
        context = getattr(err, "context", None)
        if context and problem.startswith("but "):
            problem = f"{context}, {problem}"  # "expected a single document..., but found..."
        raise ConfigError(_one_line(f"{source}{where}: not valid YAML: {problem}")) from None
    except RecursionError:
        raise ConfigError(f"{source}: not valid YAML: nested too deeply") from None
    if raw is None:
        raise ConfigError(f"{source}: (top level): the file is empty (expected site:, nodes:, ...)")
    if not isinstance(raw, dict):
        raise ConfigError(
            _one_line(
                f"{source}: (top level): expected a mapping of keys (site:, nodes:, ...),"
                f" got {_short(raw)}"
            )
        )
    try:
        return schema.model_validate(raw)
    except ValidationError as err:
        errors = err.errors()
        first = errors[0]
        more = f" (+{len(errors) - 1} more)" if len(errors) > 1 else ""
        where = _path(list(_user_loc(tuple(first["loc"]), schema)))
        what = _describe(first, schema)
        nested = _KEY_PATH.match(what)
        if nested:  # a check of a whole mapping names the key path below it
            below = nested.group(1)
            where = below if where == "(top level)" else f"{where}.{below}"
            what = nested.group(2)
        raise ConfigError(_one_line(f"{source}: {where}: {what}{more}")) from None


def load_config(path: str | Path) -> SiteConfig:
    """Read and validate a site file as a node reads it. Raises ConfigError with one line: file,
    key path, problem."""
    return load_site(path, SiteConfig)


def load_site(path: str | Path, schema: type[Site]) -> Site:
    """Read a site file and validate it against `schema`. Raises ConfigError with one line."""
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise ConfigError(f"{p}: file not found") from None
    except IsADirectoryError:
        raise ConfigError(f"{p}: is a directory, expected a YAML file") from None
    except (OSError, UnicodeDecodeError) as err:
        raise ConfigError(f"{p}: cannot read: {err}") from None
    return parse_site(text, str(p), schema)
