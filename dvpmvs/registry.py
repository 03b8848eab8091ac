"""Plugin discovery through Python entry points.

Every pluggable part has an entry-point group; a plugin distribution (ours under ``plugins/`` or
anyone's) registers factories there in its own ``pyproject.toml``::

    [project.entry-points."dvpmvs.view_selectors"]
    my_selector = "my_package.selection:make_selector"

A factory takes the plugin's parameters as a plain ``dict`` (its Hydra config without ``name``)
and returns the provider. The core never imports a concrete provider: it looks one up here by
the name written in the config.
"""

from __future__ import annotations

import logging
import typing
from collections.abc import Callable, Mapping
from functools import cache
from importlib.metadata import EntryPoint, entry_points
from typing import Any

from dvpmvs.errors import DvpmvsError
from dvpmvs.validation import check_value, simple_types

log = logging.getLogger(__name__)

__all__ = [
    "GROUPS",
    "CONFIG_GROUP",
    "PluginError",
    "PluginNotFoundError",
    "entry_points_of",
    "load_entry_points",
    "plugin_config_packages",
    "plugin_search_path",
    "available",
    "load_factory",
    "create",
    "declared_types",
    "plugin_identity",
]

# Hydra config group (and user-facing kind) -> entry-point group.
GROUPS = {
    "depth_prior": "dvpmvs.depth_priors",
    "normal_prior": "dvpmvs.normal_priors",
    "edge": "dvpmvs.edge_detectors",
    "highlight": "dvpmvs.highlight_correctors",
    "view_selector": "dvpmvs.view_selectors",
    "mask": "dvpmvs.masks",
}

# Entry points whose value is a package of extra Hydra config groups, e.g.
#   [project.entry-points."dvpmvs.configs"]  my_plugin = "my_plugin.conf"
# with my_plugin/conf/view_selector/my_selector.yaml; the CLI adds each to Hydra's search path.
CONFIG_GROUP = "dvpmvs.configs"


class PluginError(DvpmvsError, RuntimeError):
    """A plugin was found but could not be loaded or built."""


class PluginNotFoundError(DvpmvsError, LookupError):
    """No installed plugin has the requested name."""


def _entry_point_group(kind: str) -> str:
    if kind in GROUPS:
        return GROUPS[kind]
    if kind in GROUPS.values():
        return kind
    raise ValueError(f"unknown plugin kind {kind!r}; kinds: {', '.join(GROUPS)}")


def plugin_config_packages() -> list[str]:
    """The installed plugins' config packages (``CONFIG_GROUP`` entry points) whose required
    modules are installed, by name."""
    return [ep.value for ep in entry_points_of(CONFIG_GROUP) if _requirements_met(ep.value)]


def plugin_search_path() -> list[str]:
    """Hydra overrides that add the installed plugins' config packages (``CONFIG_GROUP``) to the
    search path: ``["hydra.searchpath=[pkg://a.conf,...]"]``, or ``[]`` when none is installed.

    The ``dvpmvs`` command adds them itself; with Hydra's ``compose`` API pass them along::

        with initialize_config_module(config_module="dvpmvs.conf", version_base=None):
            cfg = compose("dense", overrides=[*plugin_search_path(), "normal_prior=metric3dv2"])

    (A Hydra ``SearchPathPlugin`` in the ``hydra_plugins`` namespace would do this unasked, but
    Hydra cannot list that namespace under an editable install, which ``make setup`` makes.)
    """
    packages = [f"pkg://{package}" for package in plugin_config_packages()]
    return [f"hydra.searchpath=[{','.join(packages)}]"] if packages else []


def _requirements_met(config_package: str) -> bool:
    """Whether the modules a config package lists in its ``REQUIRES`` can be imported: presets
    of providers whose runtime is not installed (``pip install dvpmvs`` without ``[onnx]``) are
    left off the search path rather than offered and failing."""
    import importlib
    import importlib.util

    try:
        requires = getattr(importlib.import_module(config_package), "REQUIRES", ())
    except ImportError:
        return False
    return all(importlib.util.find_spec(module) is not None for module in requires)


def entry_points_of(group: str) -> list[EntryPoint]:
    """Installed entry points of one group, sorted by name.

    Two distributions registering the same name under one group is ambiguous and an error.
    """
    found: dict[str, EntryPoint] = {}
    for ep in entry_points(group=group):
        other = found.get(ep.name)
        if other is not None and other.value != ep.value:
            raise PluginError(
                f"two installed plugins register {ep.name!r} in {group}: {other.value} "
                f"({_dist_name(other)}) and {ep.value} ({_dist_name(ep)}); uninstall one"
            )
        found[ep.name] = ep
    return [found[name] for name in sorted(found)]


def load_entry_points(group: str, what: str) -> list[tuple[str, Any]]:
    """(name, loaded object) of every entry point of ``group`` whose code imports, by name. The
    run's extensions (``what``: the scoring hooks, a sweep's table columns, a report's
    sections) are optional: one whose package is absent or broken is left out with a warning
    naming it, and the command goes on without it."""
    loaded = []
    for ep in entry_points_of(group):
        try:
            loaded.append((ep.name, ep.load()))
        except ImportError as exc:
            log.warning(
                "the %s %r (%s, entry point of %s) is left out: %s",
                what,
                ep.name,
                ep.value,
                group,
                exc,
            )
    return loaded


def _dist_name(ep: EntryPoint) -> str:
    dist = getattr(ep, "dist", None)
    return dist.name if dist is not None else "unknown distribution"


def available(kind: str) -> list[str]:
    """Names of the installed plugins of one kind (``"view_selector"`` or its entry-point group)."""
    return [ep.name for ep in entry_points_of(_entry_point_group(kind))]


def load_factory(kind: str, name: str) -> Callable[[dict], Any]:
    """The factory registered under ``name`` for ``kind``; an unknown name lists the installed ones."""
    group = _entry_point_group(kind)
    eps = {ep.name: ep for ep in entry_points_of(group)}
    if name not in eps:
        installed = ", ".join(sorted(eps)) or "none"
        raise PluginNotFoundError(
            f"no {kind} plugin named {name!r} is installed (entry-point group {group}); "
            f"installed: {installed}. Install the plugin distribution that provides it "
            f"(the built-in ones come with dvpmvs; the learned priors need pip install 'dvpmvs[onnx]')"
        )
    try:
        factory = eps[name].load()
    except Exception as exc:  # an import error inside the plugin: say which plugin broke
        raise PluginError(
            f"{kind} plugin {name!r} ({eps[name].value}) failed to load: {exc}"
        ) from exc
    if not callable(factory):
        raise PluginError(f"{kind} plugin {name!r} ({eps[name].value}) is not callable")
    return factory


def declared_types(factory: Callable[[dict], Any]) -> dict[str, tuple[type, ...]]:
    """The plain types (:func:`dvpmvs.validation.simple_types`) a plugin declares for its
    parameters: the annotations of the ``__init__`` of the class its factory returns (its return
    annotation), or of the factory itself where it is that class. Parameters without a plain
    annotation are left to the plugin."""
    target = factory if isinstance(factory, type) else None
    if target is None:
        try:
            target = typing.get_type_hints(factory).get("return")
        except Exception:  # an annotation the plugin's module cannot resolve: declares nothing
            return {}
    if not isinstance(target, type):
        return {}
    try:
        hints = typing.get_type_hints(target.__init__)
    except Exception:
        return {}
    declared = {name: simple_types(hint) for name, hint in hints.items() if name != "return"}
    return {name: allowed for name, allowed in declared.items() if allowed}


def create(kind: str, config: Mapping[str, Any] | str) -> Any:
    """Build a provider from its config: ``{"name": <entry point>, <params>...}`` or just a name.
    Parameters the plugin declares a plain type for (:func:`declared_types`) are checked as the
    core's options are (``mask.allow_missing=no`` stops the run naming the key, instead of
    counting as true)."""
    if isinstance(config, str):
        name, params = config, {}
    else:
        params = dict(config)
        name = params.pop("name", None)
        if not name:
            raise ValueError(f"the {kind} config has no 'name' naming the plugin: {dict(config)}")
    factory = load_factory(kind, name)
    for key, allowed in declared_types(factory).items():
        # null is a plugin config's "not set" (its group's YAML lists every key): the plugin's own.
        if params.get(key) is not None:
            try:
                params[key] = check_value(f"{kind}.{key}", params[key], allowed)
            except ValueError as exc:
                raise PluginError(f"{kind} plugin {name!r}: {exc}") from None
    try:
        return factory(params)
    except (TypeError, ValueError) as exc:
        raise PluginError(
            f"{kind} plugin {name!r} rejected its parameters {params}: {exc}"
        ) from exc


@cache
def plugin_identity(kind: str, name: str) -> dict:
    """Which code implements a plugin: its entry point, distribution and version, and the digest
    of the sources of the package that defines it (an edited plugin is another plugin).
    Read once per process: every view's provenance asks for it."""
    import importlib.util

    from dvpmvs.digests import sources_digest

    group = _entry_point_group(kind)
    ep = {e.name: e for e in entry_points_of(group)}.get(name)
    if ep is None:
        raise PluginNotFoundError(
            f"no {kind} plugin named {name!r} is installed (entry-point group {group})"
        )
    dist = getattr(ep, "dist", None)
    package = ep.value.split(":")[0].split(".")[0]
    spec = importlib.util.find_spec(package)
    folders = list(spec.submodule_search_locations or []) if spec is not None else []
    return {
        "entry_point": ep.value,
        "distribution": dist.name if dist is not None else None,
        "version": dist.version if dist is not None else None,
        "sources": [sources_digest(folder) for folder in folders],
    }
