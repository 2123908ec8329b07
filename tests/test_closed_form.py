"""The closed-form checks (``softcrawl.verify.checks``, verification.md) with the test suite's
own tolerances, each set near the error measured at the test's resolution with a stated
margin, the convergence under mesh refinement, and a mutation per check: the same check on a
model whose E, nu, mu, g or load is off by a few percent (``ModelScales``) must fail.

The acceptance bounds a ``CheckResult`` carries are what ``softcrawl verify`` reports; these
tests do not use them.
"""

import numpy as np
import pytest

from softcrawl.fem.static import solve_static
from softcrawl.fem.state import Control
from softcrawl.verify import checks
from softcrawl.verify.checks import NOMINAL, ModelScales


def _signed(result: checks.CheckResult) -> float:
    """``got / expected - 1`` of a relative check."""
    return result.got / result.expected - 1.0


# -- cantilever: Euler-Bernoulli, O(h^2) convergence of linear tetrahedra ------------------------

def _cantilever_errors(levels: tuple[int, ...], scales: ModelScales) -> dict[str, list[float]]:
    """Signed relative tip-deflection errors per load at the given resolutions."""
    out = {}
    for load in ("tip", "gravity"):
        out[load] = []
        for lv in levels:
            got, expected = checks.cantilever_tip_deflection(checks.CANTILEVER_DIVISIONS[lv], load, scales)
            out[load].append(got / expected - 1.0)
    return out


def _richardson(coarse: float, medium: float, ratio: float = 2.0, order: float = 2.0) -> float:
    """Richardson extrapolation of two errors at element sizes ``ratio`` apart, O(h^order)."""
    r = ratio**order
    return (r * medium - coarse) / (r - 1.0)


def cantilever_agrees(scales: ModelScales = NOMINAL) -> tuple[bool, dict]:
    """The coarse (40x4) and medium (80x8) beams against Euler-Bernoulli.

    - Richardson extrapolation (O(h^2)) of the two within 0.5%: measured -0.08% (tip load) and
      +0.10% (gravity); 0.5% stays under the +0.6% shear correction of a 3-D beam of L/h = 10
      (Timoshenko), which these two meshes do not resolve. E, the tip load or g off by more
      than about 0.6% either way moves it past 0.5% (1% is tested).
    - Each mesh stiffer than the closed form (locking), by at most 17% (coarse; measured
      15.7% / 15.5%) and 4.5% (medium; measured 4.0% / 3.8%).
    - Observed order log2(e_coarse / e_medium) in [1.7, 2.4]: measured 1.98 / 2.03.
    """
    errors = _cantilever_errors((0, 1), scales)
    ok = True
    for e_c, e_m in errors.values():
        order = np.log2(e_c / e_m) if e_c * e_m > 0 else np.nan
        ok &= abs(_richardson(e_c, e_m)) <= 0.005 and -0.17 <= e_c < 0 and -0.045 <= e_m < 0 and 1.7 <= order <= 2.4
    return bool(ok), errors


@pytest.mark.slow
def test_cantilever_converges_on_the_fine_mesh():
    """Errors fall monotonically to the fine mesh (160x16): within 1% there (measured -0.59% /
    -0.40%), and the medium/fine extrapolation within 1% (the spec's bound on shear; measured
    +0.55% / +0.40%, the 3-D beam's shear correction that the finer pair starts to see)."""
    errors = _cantilever_errors((0, 1, 2), NOMINAL)
    for e in errors.values():
        assert e[0] < e[1] < e[2] < 0 and abs(e[2]) <= 0.01, errors
        assert abs(_richardson(e[1], e[2])) <= 0.01, errors


# -- corotational invariance --------------------------------------------------------------------

def corotational_agrees(scales: ModelScales = NOMINAL) -> tuple[bool, list[float]]:
    """Rigid motions: max |elastic force| / (E h^2) <= 1e-14 (measured 1.4e-15, double
    round-off); rotated loaded beam = rotated response to 1e-10 relative (measured 4.5e-12;
    the static solves converge to 1e-8 of the load, far tighter in displacement here). The
    rotated beam's E 0.1% off gives 1e-3 (anything over ~1e-9 relative fails)."""
    rigid, rotated = checks.check_corotational_invariance("coarse", scales)
    return rigid.got <= 1e-14 and rotated.got <= 1e-10, [rigid.got, rotated.got]


def test_rigid_motion_check_sees_a_tiny_stretch():
    """The 1e-14 bound on the rigid-motion force is not vacuous: a rigidly moved beam also
    stretched by 1e-12 exceeds it (measured 6.7e-14)."""
    body = checks.cantilever_model(checks.CANTILEVER_DIVISIONS[0]).bodies[0]
    R = checks._rotation([1.0, 2.0, 3.0], 17.0)
    f, _, _ = body.internal_forces((1 + 1e-12) * body.mesh.points @ R.T)
    assert np.abs(f).max() / (checks.CANTILEVER["E"] * checks.CANTILEVER["height"] ** 2) > 1e-14


# -- Lamé sphere --------------------------------------------------------------------------------

#: Per resolution: the bound on |signed error| of the inner and outer wall displacement (the
#: sign is <= 0: displacement elements are too stiff) and on |error| of their ratio u(b)/u(a),
#: which depends on nu alone (Lamé). Measured: coarse (h = 2 mm) -3.61% / -2.72%, ratio +0.92%;
#: medium (h = 1.6 mm) -1.85% / -1.28%, ratio +0.58%; margins of about 10-40% of each.
LAME_TOL = {"coarse": (0.040, 0.011), "medium": (0.021, 0.008)}


def lame_agrees(scales: ModelScales = NOMINAL) -> tuple[bool, dict]:
    """Coarse and medium spheres against Lamé (``LAME_TOL``), and their inner-wall errors
    falling with h at an observed order of at least 1.5 (O(h^2) expected; measured 3.0 on
    these unstructured meshes). E 1% stiffer or the pressure 1% low: the coarse error passes
    4% (-4.6%); E 2% softer: the medium error turns positive (+0.2%); nu off by 3% (0.009):
    the medium ratio error leaves 0.8% (-1.0% / +2.2%). E 1% softer hides in the
    discretisation error (coarse -2.6%, medium -0.9%) and passes."""
    ok, errors = True, {}
    for res, (tol, tol_ratio) in LAME_TOL.items():
        inner, outer = (_signed(r) for r in checks.check_lame_sphere(res, scales))
        ratio = (1 + outer) / (1 + inner) - 1
        errors[res] = (inner, outer, ratio)
        ok &= -tol <= min(inner, outer) and max(inner, outer) <= 0 and abs(ratio) <= tol_ratio
    e_c, e_m = errors["coarse"][0], errors["medium"][0]
    h_c, h_m = checks.LAME_MESH[:2]
    ok &= e_c * e_m > 0 and np.log(e_c / e_m) / np.log(h_c / h_m) >= 1.5
    return bool(ok), errors


@pytest.mark.slow
def test_lame_sphere_fine_mesh():
    """h = 1.25 mm: inner and outer wall within 0.7% (measured -0.52% / -0.06%), the inner
    error below the medium mesh's."""
    inner, outer = (_signed(r) for r in checks.check_lame_sphere("fine"))
    medium = _signed(checks.check_lame_sphere("medium")[0])
    assert abs(inner) <= 0.007 and abs(outer) <= 0.007 and abs(inner) < abs(medium), (inner, outer, medium)


# -- friction: incline stick / slip, sliding to rest, resting contact ----------------------------

def incline_agrees(scales: ModelScales = NOMINAL, below: float = 0.1, above: float = 0.1) -> tuple[bool, list]:
    """Stick ``below`` deg under theta*: drift over 1 s <= 1e-12 mm (measured exactly 0: the
    exact active-set contact solve sticks to round-off; 1e-12 mm is ~200 ulp of a 5 mm
    coordinate, and docs/physics.md promises below 1e-11 mm/s). Slide ``above`` deg over it:
    acceleration within 1e-6 relative of g (sin - mu cos) (measured 7.5e-9 at 0.1 deg, 6.6e-9
    at 5 deg: the quadratic fit's round-off). At 0.1 deg from theta* a friction 0.5% low
    slides where it must stick (0.3% low still sticks), and mu off by 1e-4 moves the
    acceleration by 3%, g off by 1e-4 by 1e-4: both far over 1e-6."""
    drift, accel = checks.check_incline("coarse", scales, below, above)
    return drift.got <= 1e-12 and accel.error <= 1e-6, [drift.got, accel.error]


def test_static_friction_sticks_every_contact():
    """Below theta* every contact sticks (not slow creep), on both check angles."""
    for below in (0.1, 2.0):
        _, xs, solver, _ = checks._run(checks.block_model(checks.incline_gravity(checks.THETA_STAR - below)), 1.1, 0.01)
        assert abs(xs[-1, 0] - xs[9, 0]) <= 1e-12
        assert solver.stats.n_sticking == solver.stats.n_contacts > 0


def sliding_agrees(scales: ModelScales = NOMINAL) -> tuple[bool, list[float]]:
    """Distance against implicit Euler's exact discrete answer
    (:func:`checks.sliding_distance_implicit_euler`) within 1e-5 relative (measured 8.8e-7:
    the stiff block's elastic settling) and against the continuous v0^2 / (2 mu g) within 1.3%
    (measured 1.18%: the method's first-order bias h v0 / 2); final speed <= 1e-9 mm/s
    (measured 8.3e-12). Friction or g off by 1e-4 already fails."""
    distance, speed = checks.check_sliding_to_rest("coarse", scales)
    discrete = checks.sliding_distance_implicit_euler(checks.SLIDING_V0, checks.MU * checks.G, checks.SLIDING_DT)
    rel = abs(distance.got / discrete - 1)
    return rel <= 1e-5 and distance.error <= 0.013 and speed.got <= 1e-9, [rel, distance.error, speed.got]


def test_sliding_distance_closed_form():
    """The discrete formula on a whole number of steps is v0^2 / (2 a) - h v0 / 2, and a step
    sum done by hand agrees on a fractional one."""
    assert checks.sliding_distance_implicit_euler(100.0, 50.0, 0.01) == pytest.approx(100.0 - 0.5, rel=1e-12)
    v, d = 1000.0, 0.0
    while v - 1e-3 * 11760.0 > 0:
        v -= 1e-3 * 11760.0
        d += 1e-3 * v
    assert checks.sliding_distance_implicit_euler(1000.0, 11760.0, 1e-3) == pytest.approx(d, rel=1e-12)


def resting_agrees(scales: ModelScales = NOMINAL) -> tuple[bool, list[float]]:
    """Normal force = m g within 1e-8 relative (measured 1.1e-9, the contact solve's
    tolerance), penetration within the contact distance (measured 7e-32 mm). g off by 1e-7
    fails."""
    force, penetration = checks.check_resting_contact("coarse", scales)
    return force.error <= 1e-8 and penetration.passed, [force.error, penetration.got]


def jax_incline_agrees(scales: ModelScales = NOMINAL) -> tuple[bool, list[float]]:
    """The JAX engine's float32 contact solve on this machine's device (a CPU here), the box at
    45 and 60 deg: every result within the check's own bound, 2e-6 of dt g or of the impulse
    (measured 4.8e-8 to 4.2e-7; 16 float32 rounding units leave room for another summation
    order). Friction x 0.8 (the 45-deg box slides), x 1.001 (0.12 mm/s faster slip) and g x 1.01
    (1% more normal impulse) fail."""
    results = checks.check_jax_incline("coarse", scales)
    return all(r.passed for r in results), [r.error for r in results]


# -- the PneuNet: linear in p / E, converging under refinement -------------------------------------

def _pneunet_tip_dz(mesh_size: float, pressure: float, scales: ModelScales = NOMINAL) -> float:
    """Static mean tip z displacement (mm) of the clamped PneuNet at a sim pressure (kPa)."""
    model = checks.clamped_pneunet(mesh_size, scales)
    tip = model.bodies[0].mesh.node_sets["tip"]
    res = solve_static(model, Control(np.array([pressure * scales.load])), tol=1e-8)
    return float((res.state.x[tip, 2] - model.bodies[0].mesh.points[tip, 2]).mean())


def test_pneunet_small_pressure_response_is_linear_in_p_over_e():
    """At 5 kPa (tip 1.3 mm on 115 mm) the leg is linear elastic: the tip deflection scales
    as p / E (dimensional analysis of linear elasticity). E and p both 3% up: the same
    deflection to 1e-10 (exact at any load, elastic and pressure forces scale alike; measured
    8e-14); E 3% up alone: deflection / 1.03 within 1e-4 (measured 1.2e-5, the geometric
    nonlinearity of a 1.3 mm tip deflection), so the 2.9% change of a 3% E error is seen."""
    base = _pneunet_tip_dz(8.0, 5.0)
    both = _pneunet_tip_dz(8.0, 5.0, ModelScales(youngs_modulus=1.03, load=1.03))
    stiff = _pneunet_tip_dz(8.0, 5.0, ModelScales(youngs_modulus=1.03))
    assert base < -1.0
    assert abs(both / base - 1) <= 1e-10
    assert abs(stiff / base * 1.03 - 1) <= 1e-4


def test_pneunet_static_bend_converges_under_refinement():
    """Tip compliance at 5 kPa on 8, 6 and 4 mm meshes: linear tetrahedra are too stiff, so
    it grows with refinement (measured 0.260, 0.397, 0.425 mm/kPa), the change shrinks
    (0.137 then 0.029: by 4.7x, asserted >= 3x) and the 6 mm mesh is within 10% of the 4 mm
    one (measured 6.7%). The spec gives no bend reference (its warp table maps the authors'
    own simulator to the real leg), so the finest mesh is the reference."""
    c8, c6, c4 = (-_pneunet_tip_dz(h, 5.0) / 5.0 for h in (8.0, 6.0, 4.0))
    assert c8 < c6 < c4 and (c6 - c8) >= 3 * (c4 - c6) and (c4 - c6) <= 0.10 * c4, (c8, c6, c4)


def test_pneunet_bends_toward_paper_side_monotonically():
    """Dynamic check: the tip moves down (toward the paper side) and curls more with pressure,
    past 45 deg at 350 kPa (measured 86 deg on the 8 mm mesh)."""
    table = checks.pneunet_bending(8.0, np.array([0.0, 100.0, 200.0, 350.0]), ramp=0.3, hold=0.5)
    dz, angle = table[:, 1], table[:, 2]
    assert np.all(dz[1:] < 0)
    assert np.all(np.diff(angle) > 0) and angle[-1] > 45.0


def test_pneunet_check_fails_when_the_leg_bends_the_wrong_way():
    """The qualitative check is not vacuous: a negative pressure (load scale -1) bends the
    leg away from the paper side (measured +4.0 mm and -4.0 deg at -20 kPa)."""
    body_scales = ModelScales(load=-1.0)
    table = checks.pneunet_bending(8.0, np.array([0.0, 20.0]), ramp=0.1, hold=0.1, scales=body_scales)
    assert table[-1, 1] > 0 and table[-1, 2] < 0


def test_model_scales_perturb_the_simulated_model_only():
    """NOMINAL builds the model the CLI check builds; other scales multiply its friction,
    gravity and Young's modulus."""
    m = checks.block_model(np.array([0.0, 0.0, -checks.G]), scales=ModelScales(friction=1.1, gravity=0.5,
                                                                               youngs_modulus=2.0))
    n = checks.block_model(np.array([0.0, 0.0, -checks.G]))
    assert n.floor.friction == checks.MU and m.floor.friction == pytest.approx(1.1 * checks.MU)
    assert m.gravity[2] == pytest.approx(0.5 * n.gravity[2])
    assert m.bodies[0].material.youngs_modulus == 2.0 * n.bodies[0].material.youngs_modulus


# -- every check: nominal model within the tight tolerances, wrong models rejected ----------------

AGREES = {
    "cantilever": cantilever_agrees,
    "corotational": corotational_agrees,
    "lame": lame_agrees,
    "incline": incline_agrees,
    "incline (CLI angles: -2 / +5 deg)": lambda scales=NOMINAL: incline_agrees(scales, below=2.0, above=5.0),
    "sliding": sliding_agrees,
    "resting": resting_agrees,
    "jax_incline": jax_incline_agrees,
}

#: Each mutation with the check that must reject it; the predicates' docstrings give the
#: errors they produce. Smaller perturbations of the same parameter pass where stated there.
MUTATIONS = [
    ("cantilever", ModelScales(youngs_modulus=1.01)),
    ("cantilever", ModelScales(youngs_modulus=0.99)),
    ("cantilever", ModelScales(load=1.01)),
    ("cantilever", ModelScales(gravity=0.99)),
    ("corotational", ModelScales(youngs_modulus=1.001)),
    ("lame", ModelScales(youngs_modulus=1.01)),
    ("lame", ModelScales(youngs_modulus=0.98)),
    ("lame", ModelScales(load=0.99)),
    ("lame", ModelScales(poisson_ratio=1.03)),
    ("lame", ModelScales(poisson_ratio=0.97)),
    ("incline", ModelScales(friction=0.995)),
    ("incline", ModelScales(friction=1.001)),
    ("incline", ModelScales(gravity=1.01)),
    ("sliding", ModelScales(friction=1.01)),
    ("sliding", ModelScales(friction=0.9999)),
    ("sliding", ModelScales(gravity=1.01)),
    ("resting", ModelScales(gravity=1.0001)),
    ("jax_incline", ModelScales(friction=0.8)),
    ("jax_incline", ModelScales(friction=1.001)),
    ("jax_incline", ModelScales(gravity=1.01)),
]


def _mutation_id(scales: ModelScales) -> str:
    return ",".join(f"{k}={v:g}" for k, v in vars(scales).items() if v != 1.0)


@pytest.mark.parametrize("name", list(AGREES))
def test_check_holds_within_the_tests_tolerances(name):
    ok, got = AGREES[name]()
    assert ok, got


@pytest.mark.parametrize("name, scales", MUTATIONS, ids=[f"{n}-{_mutation_id(s)}" for n, s in MUTATIONS])
def test_check_fails_on_a_wrong_model(name, scales):
    ok, got = AGREES[name](scales)
    assert not ok, got
