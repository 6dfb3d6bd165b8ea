# The public API of jaxrkpm, declared once: ``__init__.py`` loads each name lazily from here
# (lazy_loader.attach_stub), and type checkers and IDEs read it as the package's interface
# (``from m import X as X``: an explicit re-export).
from . import internal as internal, rig as rig
from .base.outcome import Outcome as Outcome
from .base.cache import use_compilation_cache as use_compilation_cache
from .base.programs import release_if_crowded as release_if_crowded
from .control.friction import (
    FrictionalSolve as FrictionalSolve,
    LagStatus as LagStatus,
    solve_frictional as solve_frictional,
)
from .control.tracking import (
    TrackResult as TrackResult,
    TrackStatus as TrackStatus,
    control_increment as control_increment,
    path_deviation as path_deviation,
    track as track,
    waypoint_table as waypoint_table,
)
from .discretise.body import Body as Body
from .discretise.constraints import Roller as Roller
from .discretise.mesh import read_mesh as read_mesh, refine_mesh as refine_mesh
from .discretise.surface import (
    cylinder as cylinder,
    half_ellipsoid as half_ellipsoid,
    lobe as lobe,
    mirrored as mirrored,
    tetrahedralise as tetrahedralise,
)
from .io.plot import (
    contact_pressures as contact_pressures,
    deformed_particles as deformed_particles,
    deformed_surface as deformed_surface,
)
from .io.output import (
    read_series as read_series,
    write_series as write_series,
    write_solution as write_solution,
)
from .mechanics.contact import (
    Arc as Arc,
    Box as Box,
    Capsule as Capsule,
    Contact as Contact,
    ContactPenetrationWarning as ContactPenetrationWarning,
    ContactResult as ContactResult,
    HalfSpace as HalfSpace,
    Sphere as Sphere,
    contact_forces as contact_forces,
)
from .mechanics.loads import Springs as Springs
from .mechanics.pressure import Pressure as Pressure
from .mechanics.materials import (
    Fung as Fung,
    Material as Material,
    NeoHookean as NeoHookean,
    Quadratic as Quadratic,
    SaintVenantKirchhoff as SaintVenantKirchhoff,
    det as det,
    fung_tensor as fung_tensor,
    green_lagrange as green_lagrange,
    pk2 as pk2,
)
from .mechanics.tissue import (
    HolzapfelGasserOgden as HolzapfelGasserOgden,
    Ogden as Ogden,
    MooneyRivlin as MooneyRivlin,
    NearlyIncompressibleNeoHookean as NearlyIncompressibleNeoHookean,
    VerondaWestmann as VerondaWestmann,
    Yeoh as Yeoh,
    bulk_modulus as bulk_modulus,
    with_barrier as with_barrier,
)
from .model.continuation import arc_length as arc_length, point_load as point_load
from .model.model import Model as Model, SolveError as SolveError
from .solvers.continuation import EquilibriumPath as EquilibriumPath, PathStatus as PathStatus
from .solvers.linalg.base import Stability as Stability
from .solvers.results import Solution as Solution, Status as Status
from .sweeps.chunk_size import ChunkChoice as ChunkChoice, choose_chunk_size as choose_chunk_size
from .sweeps.executors import worker_settings as worker_settings
from .sweeps.runner import SweepSummary as SweepSummary, sweep as sweep
from .sweeps.storage import (
    SweepFolderError as SweepFolderError,
    read_sweep as read_sweep,
    results_dataset as results_dataset,
)

__version__: str
