"""The one YAML loader of omnipipe: bounded in size, nesting and alias expansion.

Every YAML file omnipipe reads (``rig.yaml``, ``--config``, ``baseline --rig``) goes
through :func:`load_yaml_file`. PyYAML's ``safe_load`` builds an alias as a shared
reference, so a "billion laughs" document is small in memory until something walks
it (a ``repr`` in an error message, ``dataclasses.asdict``, a copy): then it grows
exponentially. This loader therefore refuses, with a :class:`ConfigError` naming
the file, before anything is constructed:

- a file larger than :data:`MAX_BYTES` (1 MB; a rig.yaml or config is a few kB);
- nesting deeper than :data:`MAX_DEPTH` (32 levels);
- a document whose node count, counting every alias as a full copy of what it
  points to, exceeds :data:`MAX_NODES` (10,000; the contract's rig.yaml has ~40).

Anchors and aliases themselves are allowed (sharing a settings block in a config
is legitimate), as long as the expanded document stays within the node budget;
a recursive alias (an anchor used inside itself) is refused.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import yaml

from omnipipe.errors import ConfigError, yaml_reason

MAX_BYTES = 1_000_000
MAX_DEPTH = 32
MAX_NODES = 10_000


class _Refused(Exception):
    """Internal: the node graph breaks a bound (message says which)."""


def _expanded_size(node: yaml.Node) -> int:
    """Nodes of the document with every alias expanded; raises _Refused past a bound.

    Shared (aliased) nodes are sized once and memoised, so the walk is linear in the
    composed graph even when the expansion is exponential.
    """
    memo: dict[int, int] = {}
    active: set[int] = set()

    def size(n: yaml.Node, depth: int) -> int:
        key = id(n)
        if key in memo:
            return memo[key]
        if key in active:
            raise _Refused("recursive alias (an anchor used inside itself)")
        if depth > MAX_DEPTH:
            raise _Refused(f"nested deeper than {MAX_DEPTH} levels")
        total = 1
        if isinstance(n, yaml.SequenceNode | yaml.MappingNode):
            active.add(key)
            children = (
                n.value
                if isinstance(n, yaml.SequenceNode)
                else [c for pair in n.value for c in pair]
            )
            for child in children:
                total += size(child, depth + 1)
                if total > MAX_NODES:
                    raise _Refused(
                        f"more than {MAX_NODES} values once aliases are expanded (an alias bomb?)"
                    )
            active.discard(key)
        memo[key] = total
        return total

    return size(node, 0)


def load_yaml_file(path: str | Path, field: str) -> Any:
    """Parse a YAML file within the bounds above.

    Args:
        path: the file.
        field: what the file is, for the error (e.g. ``"rig"``, ``"config"``).

    Returns:
        The document (None for an empty file).

    Raises:
        ConfigError: ``field`` with the file as source: not found, too large, not
            UTF-8, not YAML, or beyond a bound.
    """
    path = Path(path)
    source = str(path)
    if not path.is_file():
        raise ConfigError(field, "file not found", source)
    try:
        size = path.stat().st_size
        if size > MAX_BYTES:
            raise ConfigError(
                field, f"file too large ({size} bytes; at most {MAX_BYTES} accepted)", source
            )
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError:
        raise ConfigError(field, "not valid YAML (not UTF-8 text)", source) from None
    except OSError as exc:
        raise ConfigError(field, f"cannot read ({exc.strerror})", source) from None
    loader = yaml.SafeLoader(text)
    try:
        node = loader.get_single_node()
        if node is None:
            return None
        _expanded_size(node)
        return loader.construct_document(node)
    except _Refused as exc:
        raise ConfigError(field, f"refused: {exc}", source) from None
    except RecursionError:
        raise ConfigError(
            field, f"refused: nested deeper than {MAX_DEPTH} levels", source
        ) from None
    except yaml.YAMLError as exc:
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise ConfigError(field, f"not valid YAML ({yaml_reason(exc) or first})", source) from None
    except (ValueError, OverflowError) as exc:  # e.g. an impossible date: 2024-13-45
        raise ConfigError(field, f"not valid YAML (a value cannot be read: {exc})", source) from None
    finally:
        loader.dispose()
