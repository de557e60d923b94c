"""The configurations ``robotd replay-many`` runs every source with, and each one's digest.

Configurations are the product of

- the config files (``--config FILE``, repeatable; none: the built-in defaults), and
- the variants (``--variant 'NAME: slam.filter="ekf" frontend.detector=sift'``, repeatable; none:
  one configuration per file): ``SECTION.KEY=VALUE`` pairs separated by spaces (shell-quoted where
  a value holds one), each value read as TOML as ``--set`` reads it; ``NAME:`` is optional (the
  pairs are the name without it),

with ``--set SECTION.KEY=VALUE`` (repeatable) applied to every one. The first configuration is the
baseline the table compares the others with.

A configuration's digest is the SHA-256 of its resolved tree (every key, defaults included), so
two files that resolve to the same settings share results, and a changed default changes it.
"""

from __future__ import annotations

import hashlib
import json
import shlex
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from robotd.config import Config, config_from_dict, load_config, parse_overrides, to_dict
from robotd.core.errors import ConfigError, InputError


@dataclass(frozen=True)
class Configuration:
    """One configuration: its name in the table, the resolved tree and its digest."""

    name: str
    data: dict[str, Any]  # the resolved tree as plain JSON types (what a worker rebuilds it from)
    digest: str
    file: str | None = None
    overrides: str = ""  # the --set and variant pairs, as given

    def config(self) -> Config:
        return config_from_dict(json.loads(json.dumps(self.data)))


def config_tree(cfg: Config) -> dict[str, Any]:
    """The resolved configuration as plain JSON types (tuples as lists), keys sorted."""
    tree: dict[str, Any] = json.loads(json.dumps(to_dict(cfg), sort_keys=True))
    return tree


def config_digest(cfg: Config) -> str:
    return hashlib.sha256(json.dumps(config_tree(cfg), sort_keys=True).encode()).hexdigest()[:32]


def parse_variant(text: str) -> tuple[str, list[str]]:
    """``'NAME: a.b=1 c.d="x y"'`` -> (NAME, pairs); without ``NAME:`` the name is the pairs' text."""
    head, colon, tail = text.partition(":")
    if colon and "=" not in head and head.strip():
        name, body = head.strip(), tail
    else:
        name, body = " ".join(text.split()), text
    try:
        pairs = shlex.split(body, posix=False)
    except ValueError as exc:
        raise InputError(f"--variant {text!r}: {exc}") from None
    if not pairs:
        raise InputError(f"--variant {text!r}: no SECTION.KEY=VALUE pair")
    return name, pairs


def _merge(a: dict[str, Any], b: dict[str, Any]) -> dict[str, Any]:
    out = dict(a)
    for k, v in b.items():
        out[k] = _merge(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else v
    return out


def build_configurations(
    config_files: Sequence[str] = (), sets: Sequence[str] = (), variants: Sequence[str] = ()
) -> list[Configuration]:
    """Every (file × variant) configuration, ``sets`` applied to all; ConfigError / InputError
    naming the file, pair or variant at fault, before anything runs."""
    try:
        common = parse_overrides(list(sets))
    except ConfigError as exc:
        raise InputError(str(exc)) from None
    files: list[str | None] = list(config_files) or [None]
    stems = [Path(f).stem if f else "default" for f in files]
    if len(set(stems)) < len(stems):  # same file names in other folders: name them by path
        stems = [str(f) if f else "default" for f in files]
    parsed: list[tuple[str, list[str]] | None] = [parse_variant(v) for v in variants] or [None]
    out: list[Configuration] = []
    for f, stem in zip(files, stems):
        for var in parsed:
            overrides = common
            pairs: list[str] = list(sets)
            name = stem
            if var is not None:
                vname, vpairs = var
                try:
                    overrides = _merge(common, parse_overrides(vpairs))
                except ConfigError as exc:
                    raise InputError(f"--variant {vname!r}: {exc}") from None
                pairs += vpairs
                name = vname if f is None else f"{stem}/{vname}"
            cfg = load_config(f, overrides)
            out.append(Configuration(name, config_tree(cfg), config_digest(cfg), f, " ".join(pairs)))
    names = [c.name for c in out]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise InputError(f"replay-many: configurations named alike: {', '.join(dup)} (name the variants: 'NAME: …')")
    return out
