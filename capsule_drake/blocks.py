"""A block of the station: its config type, its check and its add, registered together.

    @block("capsule.imu", ImuConfig, check=check_imu)
    def add_imu(builder, parts, config): ...

A block's config is the scenario's field at its `key` (by default its name: `capsule.imu` is
`scenario.capsule.imu`); the block is in a station when that field holds a config of its
type (null: absent). Blocks without a key (the scene, the applied forces) are in every
station and are given the whole scenario. Several blocks may share a key when it is a
union (the EPM's drivers at `epm.driver`): the one registered for the value's type is added.

Each block may have:
- `check(config, scenario)`: at load (scenario.validate), in the station's order; raises
  ValueError (its one-line message is prefixed with the block's `where`) or ScenarioError
  (taken as it is). What the block needs of the others is checked here (`need`).
- `models(parts, config)`: before the plant is finalised (models, geometry, contact).
- `add(builder, parts, config)`: after; adds the block's systems, connects them to earlier
  blocks by the station's port names (`parts.output(name)`) and exports its own
  (`parts.export`). Build-time values other blocks need (a lens, a sample rate) go through
  `parts.share(name, value)` / `parts.shared(name)`; a block never looks another's system up.
- `start(config, colon, start_s, magnet, clearance)` (drivers only): the EPM's stage joints
  at the start (epm/paths.py, `epm_start`).

The station's order of blocks is declared in station.py (`STATION_BLOCKS`), not implied by
the order of fields or of imports.
"""

from __future__ import annotations

import dataclasses
from typing import Callable

from capsule_drake.schema import ScenarioError


@dataclasses.dataclass(frozen=True)
class Block:
    name: str                          # as in STATION_BLOCKS
    config_type: type | None           # None: in every station, given the scenario
    key: str | None                    # the scenario's field holding its config
    add: Callable | None = None        # add(builder, parts, config) after Finalize
    check: Callable | None = None      # check(config, scenario) at load
    models: Callable | None = None     # models(parts, config) before Finalize
    start: Callable | None = None      # a driver's EPM start (stage joints)
    where: str = ""                    # prefix of its check's ValueError messages

    def config_in(self, scenario):
        """This block's config in `scenario`, or None when the block is absent."""
        if self.key is None:
            return scenario
        value = field_at(scenario, self.key)
        return value if isinstance(value, self.config_type) else None


_REGISTRY: dict[str, list[Block]] = {}


def register(item: Block) -> Block:
    """Adds `item` to the registry (a second registration of a name and type replaces the
    first: a module reloaded in a notebook)."""
    blocks = _REGISTRY.setdefault(item.name, [])
    blocks[:] = [b for b in blocks if b.config_type is not item.config_type]
    blocks.append(item)
    return item


def block(name: str, config_type: type | None = None, *, key: str | None = "",
          check: Callable | None = None, models: Callable | None = None,
          start: Callable | None = None, where: str | None = None):
    """Decorator: registers `add(builder, parts, config)` as block `name` for `config_type`
    at the scenario's field `key` (default: the name; None with no config type)."""
    if key == "":
        key = name if config_type is not None else None

    def decorate(add):
        register(Block(name, config_type, key, add, check, models, start,
                       f"{key}." if where is None and key else (where or "")))
        return add
    return decorate


def registered(name: str) -> list[Block]:
    """The blocks registered under `name` (several for a union's members)."""
    return list(_REGISTRY.get(name, ()))


def all_blocks() -> list[Block]:
    return [b for blocks in _REGISTRY.values() for b in blocks]


def field_at(obj, key: str):
    """The value of the dotted field `key` of `obj` (None if any step is null)."""
    for name in key.split("."):
        if obj is None:
            return None
        obj = getattr(obj, name)
    return obj


def present(order, scenario) -> list[tuple[Block, object]]:
    """(block, config) of each block of `order` (names) that `scenario` holds, in order."""
    out = []
    for name in order:
        for item in _REGISTRY.get(name, ()):
            config = item.config_in(scenario)
            if config is not None:
                out.append((item, config))
                break
    return out


def check_blocks(order, scenario) -> None:
    """Each present block's `check`, in order; raises ScenarioError (one line)."""
    for item, config in present(order, scenario):
        if item.check is not None:
            checked(item.where, item.check, config, scenario)


def need(ok: bool, what: str) -> None:
    """Raises ScenarioError("scenario: <what>") unless `ok`: a block's check of what it
    needs of the scenario, its message naming the keys itself."""
    if not ok:
        raise ScenarioError(f"scenario: {what}")


def checked(where: str, check, *args) -> None:
    """Runs `check(*args)`; its ValueError becomes ScenarioError("scenario: <where><its first
    line>"): a block's check made of several checks, each with its own prefix."""
    try:
        check(*args)
    except ScenarioError:
        raise
    except ValueError as e:
        raise ScenarioError(f"scenario: {where}{str(e).splitlines()[0]}") from None
