# The public names of the thesis application, declared once (loaded lazily by __init__.py).
from . import (cli as cli, contact_paddle as contact_paddle, data as data, needle as needle, phantom3d as phantom3d,
               rigsim as rigsim,
               studies as studies, sweeps as sweeps, tools as tools)
from .data import (
    CP_2D as CP_2D,
    CP_3D as CP_3D,
    COMPRESSION_BREAKDOWN as COMPRESSION_BREAKDOWN,
    CUBE_MAX_ERROR as CUBE_MAX_ERROR,
    CUBE_ORIGIN as CUBE_ORIGIN,
    CUBES as CUBES,
    INCLUSIONS as INCLUSIONS,
    INCLUSIONS_3D as INCLUSIONS_3D,
    NEEDLE as NEEDLE,
    PADDLE_HALF_WIDTH as PADDLE_HALF_WIDTH,
    PATHS as PATHS,
    PHANTOM_3D as PHANTOM_3D,
    PHANTOM_OUTLINE as PHANTOM_OUTLINE,
    RIG_MODEL_BETA as RIG_MODEL_BETA,
    RIG_SETTLE_MM as RIG_SETTLE_MM,
    TABLE_5_1 as TABLE_5_1,
    TABLE_6_2 as TABLE_6_2,
    TRACKING_MINUTES as TRACKING_MINUTES,
)
# the application turns JAX's persistent compilation cache on (its CLI and notebooks call it)
from .needle import (
    DynamicRun as DynamicRun,
    HoldStatus as HoldStatus,
    NeedleTrack as NeedleTrack,
    OptimizeStatus as OptimizeStatus,
    PaddleOptimum as PaddleOptimum,
    Phantom as Phantom,
    StaticSweep as StaticSweep,
    controllability as controllability,
    dynamic_paddle as dynamic_paddle,
    final_deviation_and_gradient as final_deviation_and_gradient,
    inclusion_field as inclusion_field,
    insert as insert,
    optimize_paddle as optimize_paddle,
    spring_insertion as spring_insertion,
    static_state as static_state,
    static_sweep as static_sweep,
)
from .sweeps import (
    NeedleSweep as NeedleSweep,
    NeedleSweep3D as NeedleSweep3D,
    TrackSweep as TrackSweep,
    needle_sweep as needle_sweep,
    paddle_configurations as paddle_configurations,
)
from .phantom3d import Phantom3D as Phantom3D, ball_field as ball_field, ellipsoid_point as ellipsoid_point
from .scenarios import cube as cube, cube_path as cube_path, planar_square as planar_square
