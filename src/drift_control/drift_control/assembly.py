"""One assembly of a run's controller side: every file read once, every cross-file rule checked.

    setup = load_setup(scenario='steady_dry', vehicle='gr86', overrides=['surface.mu=0.9'])
    nmpc, selector = setup.build_nmpc(), setup.build_selector()

The nodes, the one-process closed loop, the re-run, the benches and the map builder all start
here, so they cannot disagree on which car, surface, map or tuning a run uses. A ``config``
directory holds ``defaults.yaml`` (the default vehicle, where maps live), ``vehicle/``,
``nmpc.yaml``, ``reference.yaml``, ``supervisor.yaml``, ``maps.yaml``, ``scenarios/``, ``paths/``.
Maps live per vehicle and surface: ``<maps>/<vehicle>/<surface>.npz``.
"""
from __future__ import annotations

import os
from dataclasses import dataclass, replace
from pathlib import Path as FsPath

from drift_control.ocp import NmpcParams, for_vehicle, load_nmpc_params
from drift_control.params import (ParamError, Surface, VehicleParams, config_dir, load_defaults,
                                  load_surface, load_vehicle, vehicle_file)
from drift_control.path import Path, load_path_file
from drift_control.reference import (ReferenceParams, ReferenceSelector, check_horizon_spacing,
                                     load_reference_params)
from drift_control.scenario import Scenario, load_scenario_spec, resolve_path, scenario_file
from drift_control.signals import Mode
from drift_control.supervisor import SupervisorParams, load_supervisor_params

MODES = {'full': Mode.FULL, 'torque_only': Mode.TORQUE_ONLY}


def maps_dir(config: str | os.PathLike | None = None) -> FsPath:
    """Where maps live: ``maps:`` of ``config/defaults.yaml``, relative to the config dir."""
    config = FsPath(config or config_dir())
    return (config / load_defaults(config)['maps']).resolve()


def map_file(vehicle: str, surface: str, config: str | os.PathLike | None = None) -> FsPath:
    """The equilibrium map of ``vehicle`` on ``surface`` (without suffix)."""
    return maps_dir(config) / vehicle / surface


def build_maps_command(vehicle: str, surface: str, config: str | os.PathLike | None) -> str:
    """The command line that (re)builds one map, for error messages."""
    cmd = f'scripts/build_maps.py --vehicle {vehicle} --surface {surface}'
    if config is not None and FsPath(config).resolve() != config_dir().resolve():
        cmd += f' --config-dir {config}'
    return cmd


def load_checked_map(vehicle_name: str, vehicle: VehicleParams, surface: Surface,
                     config: str | os.PathLike | None = None):
    """The map of ``vehicle_name`` on ``surface``; missing or built for other parameters is a
    ParamError naming the command that rebuilds it."""
    from drift_control.eqmap import MapError, load_map   # scipy and numpy grids: when needed
    path = map_file(vehicle_name, surface.name, config)
    rebuild = build_maps_command(vehicle_name, surface.name, config)
    try:
        eqmap = load_map(path, vehicle, surface, strict=True)
    except MapError as err:
        raise ParamError(f'{err}; rebuild: {rebuild}') from None
    built_for = eqmap.meta.get('vehicle', vehicle_name)
    if built_for != vehicle_name:
        raise ParamError(f'{path}.json: built for vehicle {built_for!r}, not {vehicle_name!r}; '
                         f'rebuild: {rebuild}')
    return eqmap


@dataclass(frozen=True)
class Setup:
    """Everything the controller side of one run needs, loaded and checked."""

    config: FsPath
    scenario: Scenario | None          # None: no scenario named (a node with its defaults)
    vehicle_name: str
    vehicle: VehicleParams
    surface: Surface                   # the named surface: the friction the controller assumes
    nmpc: NmpcParams
    reference: ReferenceParams         # radius range narrowed to the map's
    supervisor: SupervisorParams
    path: Path | None
    eqmap: object | None               # drift_control.eqmap.EquilibriumMap

    @property
    def mode(self) -> Mode:
        """The scenario's control mode (FULL without a scenario)."""
        return MODES[self.scenario.control_mode] if self.scenario else Mode.FULL

    def build_nmpc(self, mode: Mode | None = None, supervised: bool = True,
                   stamped: bool = False):
        """The NMPC for this vehicle, tuning and the named surface's friction; ``stamped``:
        its states are what their stamps say, e.g. an estimator's (``Nmpc``)."""
        from drift_control.nmpc import Nmpc   # CasADi and the compiled solver: when needed
        return Nmpc(self.vehicle, self.nmpc, self.mode if mode is None else mode,
                    mu=self.surface.mu, supervisor=self.supervisor if supervised else None,
                    stamped=stamped)

    def check_reference(self) -> None:
        """ParamError (one line) when the path asks for a drift the car cannot hold
        (``drift_control.feasibility``): before the car moves, not discovered as a spin."""
        if self.path is None or self.eqmap is None:
            return
        from drift_control.feasibility import reference_problems
        from drift_control.ocp import effective_bounds
        problems = reference_problems(self.path, self.eqmap,
                                      effective_bounds(self.vehicle, self.nmpc),
                                      self.reference.radius_min, self.reference.radius_max)
        if problems:
            more = len(problems) - 1
            raise ParamError(f'reference infeasible: path {self.path.name} asks '
                             f'{self.vehicle_name} on {self.surface.name} for a drift it cannot '
                             f'hold at {problems[0]}'
                             + (f' (and {more} more stretch{"es" if more > 1 else ""})'
                                if more else '')
                             + '; --allow-infeasible runs it anyway')

    def build_selector(self) -> ReferenceSelector:
        """The reference selector on the scenario's path and map, at the scenario's start."""
        if self.path is None or self.eqmap is None:
            raise ParamError('reference selector: needs a scenario (or path) and its map')
        from drift_control.feasibility import sideslip_limit
        from drift_control.ocp import effective_bounds
        # lookup_many and the grid are optional: a stand-in map may offer lookup alone
        limit = sideslip_limit(self.eqmap, effective_bounds(self.vehicle, self.nmpc)) \
            if hasattr(self.eqmap, 'filled') else None
        # the speed may rise as fast as the tyres' grip allows: the named surface's share of it
        params = replace(self.reference,
                         speed_rise_max=self.reference.speed_rise_max * self.surface.mu,
                         drift_speed_rise=self.reference.drift_speed_rise * self.surface.mu,
                         drift_speed_fall=self.reference.drift_speed_fall * self.surface.mu)
        if self.mode != Mode.FULL:
            # with the driver steering the entry's faster rotation would be asked of the
            # torque alone (docs/tuning_log.md: the semi-automated entries spun more often)
            params = replace(params, course_yaw_entry=False)
        selector = ReferenceSelector(self.eqmap.lookup, self.path, params,
                                     getattr(self.eqmap, 'lookup_many', None), limit)
        selector.reset(s_hint=self.scenario.initial.s if self.scenario else None)
        return selector


def load_setup(config: str | os.PathLike | None = None, scenario: str = '',
               vehicle: str | None = None, overrides=(), seed: int | None = None,
               path_file: str = '', surface: str | None = None,
               with_map: bool = True) -> Setup:
    """Load a run's controller side and check the rules between its files.

    Parameters
    ----------
    config : path, optional
        Config directory (default: ``$DRIFT_CONFIG_DIR`` or the checkout's ``config/``).
    scenario : str
        Scenario name or file; '' for none (then the default vehicle on ``surface``).
    vehicle : str, optional
        Overrides the scenario's ``vehicle:``.
    overrides : iterable of str
        ``key=value`` overrides of scenario keys.
    path_file : str
        A path file used instead of the scenario's ``path:``.
    surface : str, optional
        Surface name without a scenario (default ``dry``).
    with_map : bool
        Load and check the equilibrium map (the NMPC alone does not need it).
    """
    config = FsPath(config or config_dir())
    spec = (load_scenario_spec(scenario, overrides, config, seed, vehicle) if scenario
            else None)
    if spec is not None and spec.is_manoeuvre:
        raise ParamError(f'scenario {spec.name} is an identification manoeuvre (controller off): '
                         f'drive it with scripts/sysid_drive.py --scenario {spec.name}')
    vehicle_name = spec.vehicle if spec else (vehicle or '')
    vfile = vehicle_file(vehicle_name or None, config)
    vehicle_name = vfile.stem
    vparams = load_vehicle(vfile)
    surf = load_surface(spec.surface.name if spec else (surface or 'dry'),
                        config / 'vehicle' / 'surfaces.yaml')
    nmpc = for_vehicle(load_nmpc_params(config / 'nmpc.yaml'), vparams)   # the car's own lag
    reference = load_reference_params(config / 'reference.yaml')
    supervisor = load_supervisor_params(config / 'supervisor.yaml')
    check_horizon_spacing(reference, nmpc.dt)
    check_horizon_steps(reference, nmpc)
    path = None
    if path_file:
        path = load_path_file(path_file)
    elif spec is not None:
        path = resolve_path(spec.path, config, scenario_file(scenario, config).name)
    eqmap = None
    if with_map and path is not None:
        eqmap = load_checked_map(vehicle_name, vparams, surf, config)
        reference = narrow_to_map(reference, eqmap, path)
    return Setup(config, spec, vehicle_name, vparams, surf, nmpc, reference, supervisor, path,
                 eqmap)


def check_horizon_steps(reference: ReferenceParams, nmpc: NmpcParams) -> None:
    """A reference horizon shorter than the NMPC's would hold its last equilibrium for the rest."""
    if 0 < reference.horizon_steps < nmpc.N:
        raise ParamError(f'reference.horizon_steps: {reference.horizon_steps} equilibria for an '
                         f'NMPC of N = {nmpc.N} stages (nmpc.N): must be 0 or >= N')


def narrow_to_map(reference: ReferenceParams, eqmap, path: Path) -> ReferenceParams:
    """The selector's radius range (and flip radius) within the map's grid; a path curving
    tighter than the map's smallest radius is refused (its reference would be clamped, silently
    off the path)."""
    r_lo, r_hi = float(eqmap.radius[0]), float(eqmap.radius[-1])
    k_max = float(max(abs(path.K).max(), 1e-12))
    if 1.0 / k_max < r_lo - 1e-6:
        raise ParamError(f'path {path.name}: tightest radius {1.0 / k_max:.2f} m is below the '
                         f'map\'s smallest radius {r_lo:g} m (config/maps.yaml grid.radius_m)')
    lo, hi = max(reference.radius_min, r_lo), min(reference.radius_max, r_hi)
    if not lo < hi:
        raise ParamError(f'reference.radius_min/max [{reference.radius_min:g}, '
                         f'{reference.radius_max:g}] m do not overlap the map\'s radii '
                         f'[{r_lo:g}, {r_hi:g}] m')
    flip = reference.flip_radius_max and min(max(reference.flip_radius_max, lo), hi)
    return replace(reference, radius_min=lo, radius_max=hi, flip_radius_max=flip)


__all__ = ['MODES', 'Setup', 'build_maps_command', 'check_horizon_steps', 'load_checked_map',
           'load_setup', 'map_file', 'maps_dir', 'narrow_to_map']
