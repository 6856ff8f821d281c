"""The rendering methods a comparison runs: one small declarative entry each.

A :class:`Method` says which integrator to load, how the scene's envmap must be
rebuilt for it (``mis_compensation``) and how many shading rays one pixel sample
costs, so that equal-sample comparisons count rays (an emitter or product sample
plus a BSDF sample are 2 rays, as ``direct`` 1+1). Methods whose plugin this
process cannot load (e.g. ``sh_direct`` under an unsupported variant) are left
out with a note by :func:`available_methods`.

Each method has one role (:attr:`Method.role`), and every place that sets methods
against each other reads it here: the verdict, the sweep's aggregate and
``scripts/results_table.py``.

- :data:`PROJECT`: this package's product sampling (the methods that need its plugins);
- :data:`MITSUBA`: Mitsuba's own strategies. "The best Mitsuba strategy" of a run is the
  best of *every* method of this role in the same family that ran (:func:`mitsuba_strategies`);
- :data:`REFERENCE`: reference rows, not contenders: the exact tabulated product
  (``oracle_direct``) shows how close the SH product gets to an ideal product sampler that
  costs thousands of BSDF evaluations per sample. They run only when named (``--methods``),
  and the verdict and the sweep's winner leave them out.
"""

from __future__ import annotations

import dataclasses

import mitsuba as mi

#: Direct-lighting methods; their reference is ``path`` with max_depth 2.
DIRECT = "direct"
#: Multi-bounce methods; their reference is ``path`` with the same max_depth.
MULTI_BOUNCE = "path"

#: Roles of a method (see the module docstring).
PROJECT = "project"
MITSUBA = "mitsuba"
REFERENCE = "reference"


def is_multi_bounce(max_depth: int) -> bool:
    """Whether a comparison at Mitsuba's ``max_depth`` adds the multi-bounce family: above 2
    (2 is direct lighting: the camera ray and one bounce), or -1, Mitsuba's infinite depth."""
    return max_depth == -1 or max_depth > 2


@dataclasses.dataclass(frozen=True)
class Method:
    """One rendering strategy of a comparison.

    :param name: identifier used on the command line and in report files.
    :param label: human-readable description for tables and figures.
    :param integrator: ``mi.load_dict`` description of the integrator; for the multi-bounce
        family ``max_depth`` is added at load time.
    :param family: :data:`DIRECT` or :data:`MULTI_BOUNCE` (decides the reference).
    :param rays_per_sample: shading rays traced per pixel sample (per bounce for the
        multi-bounce family); equal-sample comparisons give each method
        ``spp * 2 / rays_per_sample`` samples.
    :param scene_params: options of the rebuilt envmap emitter (``{"mis_compensation": True}``),
        applied by :func:`.scene_setup.with_environment`; such a method is skipped on a scene
        without an envmap.
    :param plugin: integrator plugin type that must be loadable for the method to run.
    :param product_sampling: whether the method samples the environment with the SH product
        (only meaningful on scenes with an envmap).
    :param role: :data:`PROJECT`, :data:`MITSUBA` or :data:`REFERENCE` (an ideal sampler no
        renderer would pay for: left out of the default method set and never a contender in
        the verdict or a sweep's winner).
    :param by_default: run when ``--methods`` names none (reference rows never are).
    """

    name: str
    label: str
    integrator: dict
    family: str = DIRECT
    rays_per_sample: int = 2
    scene_params: dict = dataclasses.field(default_factory=dict)
    plugin: str | None = None
    product_sampling: bool = False
    role: str = MITSUBA
    by_default: bool = True

    @property
    def oracle(self) -> bool:
        """A reference row (:data:`REFERENCE`)."""
        return self.role == REFERENCE

    def load_integrator(self, max_depth: int) -> mi.Integrator:
        """Instantiate the integrator (``max_depth`` applies to the multi-bounce family)."""
        desc = dict(self.integrator)
        if self.family == MULTI_BOUNCE:
            desc["max_depth"] = max_depth
        return mi.load_dict(desc)


#: Every method a comparison can run, in report order.
METHODS: tuple[Method, ...] = (
    Method("direct", "direct 1+1 (envmap + BSDF, MIS)", {"type": "direct"}),
    Method("direct_misc", "direct 1+1, envmap with MIS compensation", {"type": "direct"},
           scene_params={"mis_compensation": True}),
    Method("env_only", "envmap sampling only (2 samples)",
           {"type": "direct", "emitter_samples": 2, "bsdf_samples": 0}),
    # Hopeless under a sun (its variance was 29-11854x direct's on the unit spheres), but the
    # best of Mitsuba's strategies under a low-contrast map: 1.24x and 1.08x direct_misc's
    # efficiency on the realistic scenes under potsdamer_platz (results/realistic_direct.json).
    # A verdict against "best Mitsuba" without it overstated the plugin's gain there.
    Method("bsdf_only", "BSDF sampling only (2 samples)",
           {"type": "direct", "emitter_samples": 0, "bsdf_samples": 2}),
    Method("sh_direct", "SH direct, a strategy per material (auto)",
           {"type": "sh_direct", "emitter_samples": 1, "bsdf_samples": 1},
           plugin="sh_direct", product_sampling=True, role=PROJECT),
    # The strategy of its name on every material: the product with the uncompensated map
    # carries both samples where the BSDF has no Dirac part; the others run the product
    # with their BSDF sample (integrators/strategy.py).
    Method("sh_product_only", "SH product sampling only (strategy product_only, 2 samples)",
           {"type": "sh_direct", "strategy": "product_only"},
           plugin="sh_direct", product_sampling=True, role=PROJECT),
    # Reference rows: the ideal the SH product is measured against (see module docstring).
    Method("oracle_direct", "reference row: exact tabulated product (oracle) + BSDF (MIS)",
           {"type": "oracle_direct", "emitter_samples": 1, "bsdf_samples": 1},
           plugin="oracle_direct", role=REFERENCE),
    Method("oracle_only", "reference row: exact tabulated product (oracle) only (2 samples)",
           {"type": "oracle_direct", "emitter_samples": 2, "bsdf_samples": 0},
           plugin="oracle_direct", role=REFERENCE),
    Method("path", "path tracer (envmap + BSDF, MIS)", {"type": "path"}, family=MULTI_BOUNCE),
    Method("sh_path", "SH path tracer, a strategy per material (auto)", {"type": "sh_path"}, family=MULTI_BOUNCE,
           plugin="sh_path", product_sampling=True, role=PROJECT),
)

#: The method every equal-time budget is measured against.
BASELINE = "direct"
MULTI_BOUNCE_BASELINE = "path"
#: Per family, the project's plugin at its defaults: what a user gets by switching the
#: integrator, and so the verdict's first line.
DEFAULT_PLUGIN_METHOD = {DIRECT: "sh_direct", MULTI_BOUNCE: "sh_path"}

#: Method names by role.
PROJECT_METHODS = frozenset(m.name for m in METHODS if m.role == PROJECT)
MITSUBA_METHODS = frozenset(m.name for m in METHODS if m.role == MITSUBA)
REFERENCE_METHODS = frozenset(m.name for m in METHODS if m.role == REFERENCE)


def role_of(name: str) -> str | None:
    """The role of method ``name``; None for a name this version does not know (an old report's)."""
    return next((m.role for m in METHODS if m.name == name), None)


def mitsuba_strategies(names, family: str = DIRECT) -> list[str]:
    """Mitsuba's own strategies of ``family`` among ``names``, in their order: the set whose best
    is "the best Mitsuba strategy" everywhere (verdict, sweep aggregate, README table)."""
    families = {m.name: m.family for m in METHODS}
    return [n for n in names if role_of(n) == MITSUBA and families[n] == family]


def method_by_name(name: str) -> Method:
    """Look a method up by name; raises ValueError listing the known names."""
    for method in METHODS:
        if method.name == name:
            return method
    raise ValueError(f"unknown method '{name}' (known: {', '.join(m.name for m in METHODS)})")


def plugin_status(plugin: str) -> str | None:
    """None if integrator ``plugin`` loads in the active variant, else why not (one line).

    The package registers its plugins for every variant it is used under
    (:mod:`mitsuba_shsampling.integrators`); under an unsupported variant loading
    them raises the reason, which is the last line of Mitsuba's message.
    """
    try:
        mi.load_dict({"type": plugin})
    except Exception as err:
        lines = str(err).strip().splitlines()
        reason = lines[-1] if lines else type(err).__name__
        return f"integrator '{plugin}' is not available in {mi.variant()} ({reason})"
    return None


def available_methods(names: list[str] | None = None, multi_bounce: bool = False
                      ) -> tuple[list[Method], list[str]]:
    """Methods to run, and notes about the ones left out.

    :param names: requested method names (None: all methods of the chosen families but the
        oracle rows).
    :param multi_bounce: include the multi-bounce family (``path`` vs ``sh_path``); the
        direct-lighting family is included unless ``names`` excludes it.
    :returns: (runnable methods in report order, one note per skipped method).
    """
    if names is not None:
        chosen = [method_by_name(n) for n in names]
    else:
        chosen = [m for m in METHODS if (m.family == DIRECT or multi_bounce) and not m.oracle and m.by_default]
    runnable, notes = [], []
    status_cache: dict[str, str | None] = {}
    for method in chosen:
        if method.plugin is not None:
            if method.plugin not in status_cache:
                status_cache[method.plugin] = plugin_status(method.plugin)
            why = status_cache[method.plugin]
            if why is not None:
                notes.append(f"skipped '{method.name}': {why}")
                continue
        runnable.append(method)
    return runnable, notes
