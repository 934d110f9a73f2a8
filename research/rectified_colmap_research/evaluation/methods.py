"""What a row of an evaluation table runs: a method and its conf, written once.

Every evaluation script (research/scripts/eval_*.py) names its rows the same way (the user
scripts, scripts/*.py, take the same ``--method sift|rectsift``):

- ``sift``: exactly plain COLMAP SIFT through the same code (no patch can pass, exact
  COLMAP calls, no depth network): ``confs["sift"]``;
- ``sift@N``: the same at a budget of N features;
- ``rectsift``: the default conf with the embedded depth network; another named conf of
  ``rectified_colmap.config.confs`` by its name;
- a variant, ``--variant NAME=JSON`` (conf overrides) or ``--variant NAME=CONF`` (a copy of
  a named conf): :func:`parse_variants`.

:func:`method_conf` gives the nested conf dict a method runs with (a script's base
overrides, e.g. ``--rect_conf``, under the method's own, the budget on top);
:func:`depth_model_of` the depth network it uses.
"""

from __future__ import annotations

import argparse
import copy
import json

from rectified_colmap.config import DEFAULT_DEPTH_MODEL, confs, merge_conf

PLAIN = "sift"
"""The plain-SIFT method every table compares against."""


def is_plain(method: str) -> bool:
    """``sift`` or ``sift@N``: plain COLMAP SIFT."""
    return method == PLAIN or method.startswith(PLAIN + "@")


def plain_budget(method: str) -> int | None:
    """N of ``sift@N``; None for any other method (ValueError for a bad N)."""
    if not method.startswith(PLAIN + "@"):
        return None
    n = method.removeprefix(PLAIN + "@")
    if not n.isdigit() or int(n) < 1:
        raise ValueError(f"{method!r}: expected sift@N with N a positive feature count")
    return int(n)


def add_variant_argument(parser: argparse.ArgumentParser, on_top_of: str = "") -> None:
    """The scripts' repeatable ``--variant NAME=JSON|CONF`` (parse it with
    :func:`parse_variants`); ``on_top_of``: the option whose overrides it goes on, if any."""
    where = f" (on top of {on_top_of})" if on_top_of else ""
    parser.add_argument(
        "--variant",
        action="append",
        default=[],
        metavar="NAME=JSON|CONF",
        help=f"an extra rectified method NAME: conf overrides as JSON{where}, or a named "
        "conf, e.g. 'nodedup={\"dedup\": {\"enabled\": false}}' or 'fast=rectsift-fast'; "
        "repeatable",
    )


def parse_variants(specs: list[str], taken: tuple[str, ...] | list[str] = ()) -> dict[str, dict]:
    """``--variant`` values -> {name: conf overrides}: NAME=JSON, or NAME=CONF for a named
    conf (a deep copy of ``confs[CONF]``). A name must be new, not in ``taken`` (the
    script's methods) and not plain SIFT's. ValueError (one line) otherwise."""
    variants: dict[str, dict] = {}
    for spec in specs:
        name, sep, js = spec.partition("=")
        if not sep or not name or name in taken or name in variants or is_plain(name):
            raise ValueError(f"--variant {spec!r}: expected a new NAME=JSON or NAME=CONF")
        if js in confs:
            variants[name] = copy.deepcopy(confs[js])
            continue
        try:
            overrides = json.loads(js)
        except json.JSONDecodeError as e:
            raise ValueError(f"--variant {name}: not a configuration name nor JSON ({e})") from None
        if not isinstance(overrides, dict):
            raise ValueError(f"--variant {name}: the JSON must be an object of conf sections")
        variants[name] = overrides
    return variants


def method_conf(
    method: str,
    variants: dict[str, dict] | None = None,
    base: dict | None = None,
    max_num_features: int | None = None,
) -> dict:
    """The nested conf dict of ``method``: plain SIFT's (``sift``, ``sift@N``: the budget N);
    else ``base`` overrides, then the method's (a variant's, or a named conf's), then
    ``max_num_features`` when given. No input is changed."""
    n = plain_budget(method) or max_num_features
    budget = {"sift": {"max_num_features": int(n)}} if n else {}
    if is_plain(method):
        return merge_conf(confs[PLAIN], budget)
    if variants and method in variants:
        own = variants[method]
    elif method in confs:
        own = confs[method]
    else:
        raise ValueError(f"{method!r}: not a method (sift, sift@N, a named conf) nor a variant")
    return merge_conf(merge_conf(base or {}, own), budget)


def depth_model_of(method: str, depth_model: str | None = None) -> str | None:
    """The depth network a method runs with: none for plain SIFT, else ``depth_model`` or
    the embedded default."""
    return None if is_plain(method) else (depth_model or DEFAULT_DEPTH_MODEL)
