"""Scene specs: what a domain is made of.

A *domain* is a source (dataset + split of its index), the sensor preset of that
source, and a *scene spec*: an ordered list of effects, each with a severity
distribution. A severity list with several names is drawn uniformly per scan;
one name is a fixed severity; the name ``"none"`` stands for zero severity (the
effect is skipped, the scan passes unchanged). The builder applies the effects in
list order.

Effects are the modules of ``omnilidar.domains.effects`` (interface in
``effects/base.py``), listed in :data:`EFFECTS` by their config name. The
imports are static on purpose: the per-stage code hash (``omnilidar.provenance``)
follows import statements, so editing an effect reruns the stages that use it.
:data:`DISPATCHES` marks them as a registry, so a domain's build hash can leave
out the effects it does not apply (and keeps those its effects import).

Specs are built from the validated ``domains`` config section
(``workflow/schemas/domains.schema.yaml``); entries that are not domains are the
section keys in :data:`SECTION_KEYS`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from types import ModuleType

import numpy as np

from omnilidar.domains.effects import beam_missing, beam_reduction, fog, rain, snow, wet_ground
from omnilidar.errors import InputError
from omnilidar.lidar.sensors import SensorSpec, get_sensor

# The effects are imported as a registry: a stage runs those its config names
# (omnilidar.provenance, ``exclude``).
DISPATCHES = ("omnilidar.domains.effects",)

EFFECTS: dict[str, ModuleType] = {
    "fog": fog,
    "snow": snow,
    "rain": rain,
    "wet_ground": wet_ground,
    "beam_reduction": beam_reduction,
    "beam_missing": beam_missing,
}

NO_EFFECT = "none"  # severity name meaning "zero severity": the effect is skipped

# Keys of the ``domains`` config section that are settings, not domains.
SECTION_KEYS = ("range_image", "corrupted", "fidelity", "tradeoff")

SOURCE_DATASETS = ("semantickitti", "kitti360", "pi3det", "nuscenes")


def effect_module(name: str) -> ModuleType:
    """The effect module registered under ``name``; InputError if unknown."""
    try:
        return EFFECTS[name]
    except KeyError:
        raise InputError(None, f"unknown effect {name!r}; known: {', '.join(EFFECTS)}") from None


@dataclass(frozen=True)
class EffectSpec:
    """One effect of a scene with its severity distribution.

    severities: named severities of the effect (or ``"none"``), drawn uniformly
        per scan; a single entry is a fixed severity.
    fidelity: numerical knobs passed to the effect (its DEFAULT_FIDELITY when empty).
    """

    name: str
    severities: tuple[str, ...]
    fidelity: dict = field(default_factory=dict)

    def __post_init__(self):
        module = effect_module(self.name)
        sev = tuple(self.severities) if not isinstance(self.severities, str) else (self.severities,)
        if not sev:
            raise InputError(None, f"effect {self.name}: needs at least one severity")
        known = (*module.SEVERITIES, NO_EFFECT)
        bad = [s for s in sev if s not in known]
        if bad:
            raise InputError(None, f"effect {self.name}: unknown severity {bad[0]!r}; known: {', '.join(known)}")
        unknown = set(self.fidelity or {}) - set(module.DEFAULT_FIDELITY)
        if unknown:
            raise InputError(None, f"effect {self.name}: unknown fidelity knobs {sorted(unknown)}; "
                                   f"known: {sorted(module.DEFAULT_FIDELITY)}")
        object.__setattr__(self, "severities", sev)
        object.__setattr__(self, "fidelity", dict(self.fidelity or {}))

    @property
    def module(self) -> ModuleType:
        return EFFECTS[self.name]

    @property
    def needs_ground(self) -> bool:
        return bool(self.module.NEEDS_GROUND) and any(s != NO_EFFECT for s in self.severities)

    def draw_severity(self, rng: np.random.Generator) -> str:
        """A severity for one scan: the fixed one, or uniform over the list."""
        if len(self.severities) == 1:
            return self.severities[0]
        return self.severities[int(rng.integers(len(self.severities)))]


@dataclass(frozen=True)
class SceneSpec:
    """An ordered list of effects; empty = the source scans unchanged."""

    effects: tuple[EffectSpec, ...] = ()

    def __post_init__(self):
        object.__setattr__(self, "effects", tuple(self.effects))

    @property
    def needs_ground(self) -> bool:
        """Whether any effect needs a ground mask (only then is ground estimated)."""
        return any(e.needs_ground for e in self.effects)

    @classmethod
    def from_config(cls, effects: list[dict], where: str = "effects") -> "SceneSpec":
        """From the config's list of ``{name, severities, fidelity}`` dicts."""
        specs = []
        for i, item in enumerate(effects or []):
            try:
                specs.append(EffectSpec(item["name"], tuple(item.get("severities", ())), item.get("fidelity") or {}))
            except KeyError:
                raise InputError(None, f"{where}[{i}]: needs a 'name'") from None
            except InputError as err:
                raise InputError(None, f"{where}[{i}]: {err.problem}") from None
        return cls(tuple(specs))


@dataclass(frozen=True)
class DomainSpec:
    """A domain to build: source split, sensor, scene spec and sharding.

    name: config key (``vehicle``, ``wet_ground``, ...); label: the name the
    generator knows it by (its prompt-pool key, e.g. ``WetGround``); id: the
    generator's integer domain id.
    """

    name: str
    id: int
    label: str
    dataset: str
    split: str
    sensor_name: str
    scene: SceneSpec
    num_shards: int = 1
    max_scans: int | None = None

    @property
    def sensor(self) -> SensorSpec:
        return get_sensor(self.sensor_name)

    def scan_indices(self, num_available: int, shard: int, num_shards: int | None = None) -> list[int]:
        """Indices (into the source split) of the scans shard ``shard`` builds:
        every ``num_shards``-th scan from ``shard`` on, within ``max_scans``."""
        n = self.num_shards if num_shards is None else num_shards
        if n < 1 or not 0 <= shard < n:
            raise InputError(None, f"domain {self.name}: shard {shard} is not in 0..{n - 1}")
        total = num_available if self.max_scans is None else min(num_available, self.max_scans)
        return list(range(shard, total, n))


def domain_names(settings: dict) -> list[str]:
    """The domain keys of a ``domains`` config section, in config order."""
    return [k for k in settings if k not in SECTION_KEYS]


def domain_from_config(name: str, cfg: dict) -> DomainSpec:
    where = f"domains.{name}"
    for key in ("id", "dataset", "split", "sensor"):
        if key not in cfg:
            raise InputError(None, f"{where}: missing {key!r}")
    if cfg["dataset"] not in SOURCE_DATASETS:
        raise InputError(None, f"{where}.dataset: unknown dataset {cfg['dataset']!r}; known: {', '.join(SOURCE_DATASETS)}")
    try:
        get_sensor(cfg["sensor"])
    except InputError as err:
        raise InputError(None, f"{where}.sensor: {err.problem}") from None
    return DomainSpec(
        name=name,
        id=int(cfg["id"]),
        label=str(cfg.get("label") or name),
        dataset=cfg["dataset"],
        split=cfg["split"],
        sensor_name=cfg["sensor"],
        scene=SceneSpec.from_config(cfg.get("effects", []), f"{where}.effects"),
        num_shards=int(cfg.get("num_shards", 1)),
        max_scans=cfg.get("max_scans"),
    )


def domains_from_settings(settings: dict) -> dict[str, DomainSpec]:
    """Every domain of a validated ``domains`` section; ids and labels must be unique."""
    specs = {name: domain_from_config(name, settings[name]) for name in domain_names(settings)}
    for attr in ("id", "label"):
        seen: dict = {}
        for spec in specs.values():
            value = getattr(spec, attr)
            if value in seen:
                raise InputError(None, f"domains.{spec.name}: {attr} {value!r} is also used by domains.{seen[value]}")
            seen[value] = spec.name
    return specs


def get_domain(settings: dict, name: str) -> DomainSpec:
    """One domain of the section; InputError naming the known ones if absent."""
    names = domain_names(settings)
    if name not in names:
        raise InputError(None, f"unknown domain {name!r}; configured: {', '.join(names) or 'none'}")
    return domains_from_settings(settings)[name]
