"""The static model of the JAX engine: array pytrees built from reduced :class:`~softcrawl.robot.Robot` s.

Three parts (module doc of :mod:`softcrawl.jaxsim`):

* :class:`LegPart` — the shipped leg reduction in its part frame, shared by every leg of every
  robot: the RID elements (restricted to their nodes), the cavity triangles, the collision and
  attachment nodes, each with its basis rows.
* :class:`DiskPart` — the floating-frame disk (:class:`~softcrawl.reduction.floating.FloatingFrameBody`),
  shared: rest positions, masses, ``K_0`` and ``A_0^-1`` dense.
* :class:`RobotData` — per robot (a leading batch axis when stacked): each leg slot's rotation,
  translation, regulator channel and mask, and the disk side of its attachments.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np

from softcrawl.jaxsim.contact import check_solver
from softcrawl.jaxsim.factor import CHOLESKY_FORMS
from softcrawl.jaxsim.legs import RID_FORMS, frame_rows
from softcrawl.reduction.floating import FloatingFrameBody
from softcrawl.robot.actuation import PressureCalibration

#: Disk nodes of one attachment point (a barycentric tetrahedron; a node hit exactly pads with 0 weights).
DISK_POINT_NODES = 4


def register_pytree(cls):
    """Register a dataclass of arrays (fields with ``metadata={"static": True}`` are static)."""
    fields = dataclasses.fields(cls)
    data = [f.name for f in fields if not f.metadata.get("static")]
    meta = [f.name for f in fields if f.metadata.get("static")]
    return jax.tree_util.register_dataclass(cls, data_fields=data, meta_fields=meta)


def static(default=dataclasses.MISSING):
    """A static (hashable, not traced) field of a pytree dataclass."""
    return dataclasses.field(default=default, metadata={"static": True})


@dataclass(frozen=True)
class Family:
    """One RID element family (tetrahedra k = 4, r = 6; paper triangles k = 3, r = 3), part frame.

    Attributes:
        conn: ``(E, k)`` indices of the RID nodes (the rows of :attr:`LegPart.rid_affine`).
        factors: ``(E, r, 3(k - 1))`` ``C~_e`` (sqrt(mN/mm), ECSW weight included).
        rest_terms: ``(E, r)`` ``s0_e``.
        rows: ``(E, 3(k - 1), m')`` edge basis rows of the strain modes.
        stiffness: ``(M' E, m'(m' + 1)/2)`` each element's share of ``K_r`` per quadratic
            monomial of its frame, which the GPU's form of the RID terms contracts
            (:func:`softcrawl.jaxsim.legs.frame_stiffness`), formed once before a loop of steps
            (:func:`softcrawl.jaxsim.engine.shared_parts`), or None: formed in each step.
        kernel_rows: ``rows`` as the GPU's RID kernel reads them, formed once before a loop of
            steps as ``stiffness`` is (:func:`softcrawl.jaxsim.ridkernel.kernel_rows`), or None.
    """

    conn: object
    factors: object
    rest_terms: object
    rows: object
    stiffness: object = None
    kernel_rows: object = None


@dataclass(frozen=True)
class LegPart:
    """The leg reduction, part frame (mm, kg), shared by all legs.

    Attributes:
        strain_modes: ``(m',)`` modes with internal forces; mode_slots: ``(m,)`` each mode's
            position among them, ``m'`` for the others (the stiffness and forces of the strain
            modes placed among all modes by a gather).
        mass: ``(m, m)`` reduced mass, kg; mass_rows: ``(3, m)`` ``sum_n m_n Phi_n`` (gravity
            load ``mass_rows^T R_b^T g``).
        rid_affine: ``(nr, 3, m + 1)`` the RID nodes' basis rows and rest positions, ``[Phi_n,
            X_n]``: part-frame positions ``X_n + Phi_n q`` are ``rid_affine @ (q, 1)``, mm (one
            product, no rest positions broadcast over the batch).
        families: the RID families (:class:`Family`).
        cavity_rest, cavity_basis: ``(c, 3)``, ``(c, 3, m)`` of the cavity nodes; cavity_tris:
            ``(T, 3)`` indices into them.
        cavity_terms: ``((m + 1)(m + 2)/2, m)`` the cavity load per kPa as the quadratic
            polynomial it is in ``q``: the coefficients of the products ``q'_i q'_j`` (``i <= j``,
            ``np.triu_indices(m + 1)`` order) of ``q' = (q, 1)``, mN/kPa
            (:func:`cavity_polynomial`).
        coll_affine: ``(nc, 3, m + 1)`` the collision nodes' basis rows and rest positions, ``[Phi_n,
            X_n]``: part-frame positions ``X_n + Phi_n q`` are ``coll_affine @ (q, 1)``, mm
            (:func:`softcrawl.jaxsim.delassus.leg_height_terms`).
        att_affine: ``(F, 3, m + 1)`` the weighted attachment patches' basis rows and rest
            positions, ``[Phi_f, X_f]``: their part-frame positions are ``att_affine @ (q, 1)``, mm.
        basis: ``(n, 3, m)`` the basis rows of every node (node speeds ``|Phi_n qdot|``, mm/s).
    """

    strain_modes: object
    mode_slots: object
    mass: object
    mass_rows: object
    rid_affine: object
    families: tuple
    cavity_rest: object
    cavity_basis: object
    cavity_tris: object
    cavity_terms: object
    coll_affine: object
    att_affine: object
    basis: object


@dataclass(frozen=True)
class DiskPart:
    """The floating-frame disk, shared (placed rest configuration).

    Attributes:
        rest: ``(n, 3)`` rest positions, mm; weighted_rest: ``(n, 3)`` rest minus the centre of
            mass, times the mass fractions (Kabsch input).
        step_operator: ``(3n, 6n + 3)`` the free step's operator on ``(R^T v, R^T x - X, R^T g)``
            (:func:`disk_step_operator`); inverse: ``(3n, 3n)`` ``A_0^-1`` of the step matrix, 1/kg.
        collision: ``(nc,)`` collision nodes; reward_node: the top-centre node (int).
    """

    rest: object
    weighted_rest: object
    step_operator: object
    inverse: object
    collision: object
    reward_node: int = static()


@dataclass(frozen=True)
class RobotData:
    """Per robot (``L`` leg slots, padded with masked legs).

    Attributes:
        leg_mask: ``(L,)`` bool; rotation: ``(L, 3, 3)`` part -> world; translation: ``(L, 3)``, mm;
        channel: ``(L,)`` regulator channel ``0..R-1`` of each leg.
        disk_nodes, disk_weights: ``(L, F, 4)`` the disk side of each attachment point.
        att_gram: ``(L F, L F, 3, 3)`` ``E^T A_0^-1 E`` of the attachment points (body frame).
    """

    leg_mask: object
    rotation: object
    translation: object
    channel: object
    disk_nodes: object
    disk_weights: object
    att_gram: object


#: The forms of :attr:`Settings.delassus`.
DELASSUS_FORMS = ("dense", "dense16", "fused16", "blocks")


@dataclass(frozen=True)
class Settings:
    """Scalar settings (static: a change recompiles).

    Attributes:
        dt: s; rayleigh_mass (1/s), rayleigh_stiffness (s); gravity: ``(3,)`` mm/s^2;
        floor: whether there is a floor; floor_z, contact_distance: mm; friction: Coulomb mu;
        disk_contacts, leg_contacts: contact points of the disk and of each leg slot per step
            (each body's lowest predicted gaps; 0 without a floor);
        solver: the contact solver, ``"apgd"`` or ``"pgs"``, and iterations: its iterations
            (:func:`softcrawl.jaxsim.contact.solve_contacts`);
        calibration: ``(a, b)`` of ``sim = max(a real + b, 0)``; rate: regulator slew, kPa/s;
        channels: ``R``, the pressure channels (regulators of the robots' design space; 3 in the
            paper's): the length of every robot's regulator pressures;
        delassus: how the accelerated gradient applies the contacts' Delassus operator:
            ``"dense"`` (one matrix-vector product per iteration, the fewest kernels),
            ``"dense16"`` (the same, the iterations reading the operator in float16 by iterative
            refinement, :func:`softcrawl.jaxsim.contact.apgd_coulomb`'s ``storage``: half the
            bytes; a CPU reads its operator whole,
            ``jax.lax.platform_dependent``: there it stays in cache and float16 would only add
            conversions), ``"fused16"`` (``"dense16"``'s solve, its scaling and rounding
            included, in one kernel on a GPU, :mod:`softcrawl.jaxsim.fused`: the operator read
            from memory once; CUDA only: a CPU runs ``"dense"``, other platforms ``"dense16"``;
            :func:`build_model`'s default in float32) or ``"blocks"``
            (:class:`softcrawl.jaxsim.delassus.DelassusBlocks`: 2.6 times fewer bytes per
            iteration than ``"dense"``, more kernels), the same operator;
        rid_form: the form of the legs' RID terms (:func:`softcrawl.jaxsim.legs.rid_terms`),
            ``"rows"``, ``"pairs"`` or ``"kernel"`` (one GPU kernel per leg, CUDA only), or None
            (the default: by platform);
        cholesky: how the step inverts the Cholesky factors of the legs' step matrices and the
            attachment block (:func:`softcrawl.jaxsim.factor.cholesky_inverse`,
            :func:`~softcrawl.jaxsim.factor.inverse_spd`): ``"library"`` (a factorisation and a
            triangular solve) or ``"kernel"`` (one kernel on a GPU each, the block's by sweeps;
            CUDA only: other platforms, a CPU among them, run the library's; :func:`build_model`'s
            default in float32).

    "CUDA" for a kernel form means an NVIDIA GPU of compute capability 8.0 or newer (Ampere on:
    XLA compiles Pallas' Triton kernels for those only); on older ones (a T4, a V100) the step
    takes the form it takes on other platforms (:mod:`softcrawl.jaxsim.gpu`).
    """

    dt: float
    rayleigh_mass: float
    rayleigh_stiffness: float
    gravity: tuple
    floor: bool
    floor_z: float
    contact_distance: float
    friction: float
    disk_contacts: int
    leg_contacts: int
    solver: str
    iterations: int
    calibration: tuple
    rate: float
    channels: int = 3
    delassus: str = "dense"
    rid_form: str | None = None
    cholesky: str = "library"

    def __post_init__(self):
        """Raises: ValueError: a ``delassus`` not among :data:`DELASSUS_FORMS`, a ``rid_form``
        other than None or one of :data:`softcrawl.jaxsim.legs.RID_FORMS`, a ``cholesky`` not
        among :data:`softcrawl.jaxsim.factor.CHOLESKY_FORMS`."""
        if self.delassus not in DELASSUS_FORMS:
            raise ValueError(f"settings.delassus must be one of {DELASSUS_FORMS}, not {self.delassus!r}")
        if self.rid_form is not None and self.rid_form not in RID_FORMS:
            raise ValueError(f"settings.rid_form must be None or one of {RID_FORMS}, not {self.rid_form!r}")
        if self.cholesky not in CHOLESKY_FORMS:
            raise ValueError(f"settings.cholesky must be one of {CHOLESKY_FORMS}, not {self.cholesky!r}")

    @property
    def delassus_storage(self):
        """The dtype name in which the accelerated gradient's iterations read the dense operator
        (:func:`softcrawl.jaxsim.contact.apgd_coulomb`'s ``storage``), None for the arrays' own."""
        return "float16" if self.delassus in ("dense16", "fused16") else None


@dataclass(frozen=True)
class Model:
    """The static model: shared parts, per-robot data (leading batch axis if stacked), settings."""

    leg: LegPart
    disk: DiskPart
    robot: RobotData
    settings: Settings = static()


for _cls in (Family, LegPart, DiskPart, RobotData, Model):
    register_pytree(_cls)


def _same_part(a, b) -> bool:
    """Whether two leg reductions hold the same basis, RID elements and weights."""
    return a is b or all(np.array_equal(getattr(a, k), getattr(b, k))
                         for k in ("basis", "tet_rid", "tet_weights", "tri_rid", "tri_weights"))


def _patches(robot) -> list[tuple[np.ndarray, np.ndarray]]:
    """The attachment patches of a robot's first leg: per point its part nodes and weights."""
    return [(np.asarray(a.a.nodes), np.asarray(a.a.weights, float))
            for a in robot.model.attachments if a.a.body == robot.legs[0].body]


def _leg_part(robot) -> LegPart:
    """The shared leg data of a reduced robot."""
    rb = robot.reduced[robot.legs[0].body]
    body = rb.body
    Phi = rb.part.basis
    X = rb.part.mesh.points
    n, m = X.shape[0], Phi.shape[1]
    rows = Phi.reshape(n, 3, m)
    facs = rb.element_factors
    rid = np.unique(np.concatenate([f.conn.ravel() for f in facs]))
    remap = np.full(n, -1, np.int64)
    remap[rid] = np.arange(len(rid))
    for f in facs:  # the pairs form takes the frame rows legs.frame_rows names, no others
        C = np.abs(np.asarray(f.factors)).reshape(*f.factors.shape[:2], -1, 3)
        if C[..., frame_rows(C.shape[2]):].max(initial=0.0) > 1e-9 * C.max(initial=0.0):
            raise ValueError("the JAX engine steps membrane triangles only: this leg reduction's triangle "
                             "factors act on the elements' normal components")
    families = tuple(Family(remap[f.conn], f.factors, f.rest_terms, f.rows) for f in facs)
    tris = np.concatenate([np.asarray(c.triangles, np.int64) for c in body.cavities])
    cav, local = np.unique(tris, return_inverse=True)
    coll = np.asarray(body.collision_nodes, np.int64)
    patches = _patches(robot)
    att_affine = np.stack([np.einsum("n,nam->am", w, _affine(X, rows, nd)) for nd, w in patches])
    mass_rows = np.einsum("n,nam->am", body.nodal_mass, rows)
    sm = np.asarray(rb.strain_modes)
    slots = np.full(m, len(sm), np.int32)
    slots[sm] = np.arange(len(sm))
    part = LegPart(sm, slots, rb.reduced_mass, mass_rows, _affine(X, rows, rid), families,
                   X[cav], rows[cav], local.reshape(tris.shape), cavity_polynomial(X, rows, tris),
                   _affine(X, rows, coll), att_affine, rows)
    return part


def _affine(X: np.ndarray, rows: np.ndarray, nodes: np.ndarray) -> np.ndarray:
    """``(len(nodes), 3, m + 1)`` the ``nodes``' basis rows ``rows`` ``(n, 3, m)`` and rest
    positions ``X`` ``(n, 3)``, ``[Phi_n, X_n]``: their positions ``X_n + Phi_n q`` are one
    product with ``(q, 1)``."""
    return np.concatenate([rows[nodes], X[nodes][:, :, None]], axis=2)


#: The Levi-Civita symbol ``eps[i, j, k]`` (``(a x b)_i = eps_ijk a_j b_k``).
_LEVI_CIVITA = np.zeros((3, 3, 3))
_LEVI_CIVITA[0, 1, 2] = _LEVI_CIVITA[1, 2, 0] = _LEVI_CIVITA[2, 0, 1] = 1.0
_LEVI_CIVITA[0, 2, 1] = _LEVI_CIVITA[2, 1, 0] = _LEVI_CIVITA[1, 0, 2] = -1.0


def cavity_polynomial(X: np.ndarray, rows: np.ndarray, tris: np.ndarray) -> np.ndarray:
    """The cavity's follower load per kPa as the quadratic polynomial it is in the modal
    displacement ``q``.

    Each cavity triangle ``t`` gives each of its vertices ``w_t = (p/6) e1 x e2`` (its area
    vector times ``p/3``; physics.md, "Pneumatic actuation"), projected on the vertices' basis
    rows ``S_t = Phi_t0 + Phi_t1 + Phi_t2``. Its edges are linear in ``q``, ``e1 = a + A q``,
    ``e2 = b + B q``, so the load per kPa is exactly

        (1/6) sum_t S_t^T (a x b + a x B q + A q x b + A q x B q),

    a quadratic polynomial in ``q``, summed here once in float64: a step then takes the products
    of ``q' = (q, 1)`` in pairs and one product with these coefficients, instead of the cavity's
    positions, cross products and projection.

    Args:
        X: ``(n, 3)`` rest positions, mm; rows: ``(n, 3, m)`` basis rows of the part's nodes;
            tris: ``(T, 3)`` the cavity triangles' node indices (outward normals).

    Returns:
        ``((m + 1)(m + 2)/2, m)``: the coefficient of ``q'_i q'_j`` (``i <= j``,
        ``np.triu_indices(m + 1)`` order; ``q'_m = 1``) in each mode's load, mN/kPa per mm^2,
        mm or 1 of ``q``.
    """
    x0, x1, x2 = (X[tris[:, k]] for k in range(3))
    p0, p1, p2 = (rows[tris[:, k]] for k in range(3))
    A = np.concatenate([p1 - p0, (x1 - x0)[:, :, None]], axis=2)  # e1 = A q'
    B = np.concatenate([p2 - p0, (x2 - x0)[:, :, None]], axis=2)  # e2 = B q'
    T, m = len(tris), rows.shape[2]
    M = np.einsum("ijk,tio->tjko", _LEVI_CIVITA, p0 + p1 + p2) / 6.0  # (S_t^T (u x v))_o = M_jko u_j v_k
    N = np.einsum("tjko,tjr->tkor", M, A, optimize=True)
    Q = (B.reshape(T * 3, m + 1).T @ N.reshape(T * 3, m * (m + 1))).reshape(m + 1, m, m + 1)  # Q[s, o, r]
    i, j = np.triu_indices(m + 1)
    return np.where((i == j)[:, None], Q[j, :, i], Q[j, :, i] + Q[i, :, j])


def disk_inverse(robot) -> np.ndarray:
    """``A_0^-1`` ``(3n, 3n)`` float64 of a reduced robot's floating-frame disk: the inverse of its
    linearly implicit step matrix ``A_0 = h (h + beta) K_0 + (1 + h alpha) M`` (Rayleigh damping
    ``alpha`` mass, ``beta`` stiffness; physics.md, "Time stepping") at rest, dense."""
    fb = robot.reduced[robot.disk_body]
    h, rM, rK = robot.config.dt, robot.model.rayleigh_mass, robot.model.rayleigh_stiffness
    A0 = h * (h + rK) * fb.rest_stiffness.toarray() + np.diag((1 + h * rM) * np.repeat(fb.body.nodal_mass, 3))
    return np.linalg.inv(A0)


def disk_step_operator(robot, inverse: np.ndarray) -> np.ndarray:
    """``[A_0^-1 M | -h A_0^-1 K_0 | h A_0^-1 (m ⊗ I_3)]`` ``(3n, 6n + 3)`` float64 of a reduced
    robot's floating-frame disk: its free step's velocities, floating frame, from the velocities,
    the displacements from rest (mm) and gravity (mm/s^2) in that frame (:mod:`softcrawl.jaxsim.disk`,
    its module doc; ``h`` the robot's step, ``M = diag(m ⊗ 1_3)`` the lumped masses, kg).

    Args:
        inverse: the disk's ``A_0^-1`` ``(3n, 3n)``, 1/kg (:func:`disk_inverse`).
    """
    fb = robot.reduced[robot.disk_body]
    h, mass = robot.config.dt, np.asarray(fb.body.nodal_mass, np.float64)
    n = mass.shape[0]
    gravity = h * np.einsum("ina,n->ia", inverse.reshape(3 * n, n, 3), mass)
    return np.concatenate([inverse * np.repeat(mass, 3)[None, :], -h * (inverse @ fb.rest_stiffness.toarray()),
                           gravity], axis=1)


def _disk_part(robot) -> DiskPart:
    """The shared floating-frame disk data of a reduced robot."""
    fb = robot.reduced[robot.disk_body]
    node = robot.reward_node - int(robot.model.node_offsets[robot.disk_body])
    inverse = disk_inverse(robot)
    return DiskPart(fb.body.mesh.points, fb.weighted_rest, disk_step_operator(robot, inverse),
                    inverse, np.asarray(fb.body.collision_nodes, np.int64), node)


def leg_rows(robot) -> tuple[np.ndarray, ...]:
    """Per leg of a reduced robot, in its order (:attr:`~softcrawl.robot.Robot.legs`):
    ``(rotation (l, 3, 3) part -> world, translation (l, 3) mm, channel (l,), disk_nodes
    (l, F, 4), disk_weights (l, F, 4))``, the disk side of each of its ``F`` attachment points
    (a point on fewer than 4 disk nodes padded with node 0, weight 0).

    Raises:
        ValueError: an attachment that does not tie a leg to the disk.
    """
    F = sum(1 for a in robot.model.attachments if a.a.body == robot.legs[0].body)
    n = len(robot.legs)
    rot, trans = np.zeros((n, 3, 3)), np.zeros((n, 3))
    channel = np.zeros(n, np.int64)
    dn = np.zeros((n, F, DISK_POINT_NODES), np.int64)
    dw = np.zeros((n, F, DISK_POINT_NODES))
    for j, leg in enumerate(robot.legs):
        rb = robot.reduced[leg.body]
        rot[j], channel[j] = rb.rotation, leg.channel
        trans[j] = (rb.body.mesh.points - rb.part.mesh.points @ rb.rotation.T).mean(axis=0)
        refs = [a.b for a in robot.model.attachments if a.a.body == leg.body]
        for a, ref in enumerate(refs):
            if ref.body != robot.disk_body:
                raise ValueError("the JAX engine needs every attachment to tie a leg to the disk")
            dn[j, a, :len(ref.nodes)] = ref.nodes
            dw[j, a, :len(ref.nodes)] = ref.weights
    return rot, trans, channel, dn, dw


def attachment_gram(nodes: np.ndarray, weights: np.ndarray, inverse: np.ndarray,
                    cols: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
    """``E_p^T A_0^-1 E_q`` ``(P, Q, 3, 3)`` of disk points ``p`` (``nodes``, ``weights``
    ``(P, 4)``) and ``q`` (``cols``, default the same points): the disk's share of the
    attachment blocks of the Delassus operator, body frame, 1/kg (mm/s per mN s of impulse).

    Args:
        inverse: the disk's ``A_0^-1`` ``(3n, 3n)``, 1/kg (:func:`disk_inverse`).
    """
    cn, cw = (nodes, weights) if cols is None else cols
    n = inverse.shape[0] // 3
    G = inverse.reshape(n, 3, n, 3).transpose(0, 2, 1, 3)
    return np.einsum("pi,qj,piqjab->pqab", weights, cw, G[nodes[:, :, None, None], cn[None, None, :, :]])


def _robot_data(robot, n_slots: int, inverse: np.ndarray) -> RobotData:
    """One robot's :class:`RobotData` with ``n_slots`` leg slots (the first ``len(robot.legs)`` used;
    the others masked: identity rotation, zero translation, channel, nodes and weights)."""
    rows = leg_rows(robot)
    L, n = n_slots, len(robot.legs)
    mask = np.arange(L) < n
    rot = np.tile(np.eye(3), (L, 1, 1))
    rot[:n] = rows[0]
    trans, channel, dn, dw = (np.concatenate([a, np.zeros((L - n,) + a.shape[1:], a.dtype)]) for a in rows[1:])
    gram = attachment_gram(dn.reshape(-1, DISK_POINT_NODES), dw.reshape(-1, DISK_POINT_NODES), inverse)
    return RobotData(mask, rot, trans, channel, dn, dw, gram)


def build_model(robots, leg_contacts: int = 12, disk_contacts: int = 8, solver: str = "apgd",
                iterations: int | None = None, dtype=None, n_slots: int | None = None, floor: bool = True,
                calibration: PressureCalibration = PressureCalibration(), rate_kpa_s: float = 150.0,
                delassus: str | None = None, cholesky: str | None = None) -> Model:
    """The static model of a batch of reduced robots (stacked per-robot data, leading axis = robot).

    Args:
        robots: reduced :class:`~softcrawl.robot.Robot` s (``RobotConfig(model="reduced")``, floating
            disk) sharing one leg reduction, disk mesh, config and pressure channels (the
            regulators of their design space), of any slot angles.
        leg_contacts, disk_contacts: floor contact points kept per leg and for the disk each step
            (each body's lowest predicted gaps).
        solver: the contact solver, ``"apgd"`` (accelerated projected gradient, the default) or
            ``"pgs"`` (projected Gauss-Seidel, the CPU engine's iteration);
        iterations: its iterations per step (default
            :data:`softcrawl.jaxsim.contact.DEFAULT_ITERATIONS` of the solver).
        dtype: array precision (default float64 if ``jax_enable_x64`` is on, else float32).
        n_slots: leg slots per robot (default: the most legs of any robot; fewer are masked).
        floor: False leaves the floor out (a robot hanging free).
        calibration: the real-to-sim pressure warp; rate_kpa_s: the regulators' slew limit, kPa/s
            (:class:`softcrawl.robot.RegulatorBank`).
        delassus, cholesky: :attr:`Settings.delassus` and :attr:`Settings.cholesky` (defaults
            ``"fused16"`` and ``"kernel"`` in float32: a GPU's fastest step, measured on an H200,
            ``benchmarks/RESULTS.md``, and on a CPU the same step as ``"dense"`` and
            ``"library"``; ``"dense"`` and ``"library"`` in float64: a float64 engine is the one
            that verifies, and keeps its operator whole and its factorisations the library's).

    Raises:
        ValueError: an empty batch, a robot that is not reduced with a floating disk, robots
            that differ in their leg reduction, disk, attachments or settings, too few slots, an
            unknown solver or fewer than one iteration, an unknown ``delassus`` or
            ``cholesky``, RID triangles that are not membranes (factors on their normal
            components).
    """
    iterations = check_solver(solver, iterations)
    robots = list(robots)
    if not robots:
        raise ValueError("build_model needs at least one robot")
    for r in robots:
        if not r.reduced or not isinstance(r.reduced.get(r.disk_body), FloatingFrameBody) or r.model.floor is None:
            raise ValueError("the JAX engine needs reduced robots with a floating-frame disk and a floor")
    first = robots[0]
    leg, disk = _leg_part(first), _disk_part(first)
    key = [nd.tobytes() + w.tobytes() for nd, w in _patches(first)]
    L = n_slots or max(len(r.legs) for r in robots)
    for r in robots[1:]:
        if (not _same_part(r.reduced[r.legs[0].body].part, first.reduced[first.legs[0].body].part)
                or r.config != first.config or [nd.tobytes() + w.tobytes() for nd, w in _patches(r)] != key
                or not np.array_equal(r.model.bodies[r.disk_body].mesh.points, disk.rest)):
            raise ValueError("robots of one JAX model must share the leg reduction, disk, attachments and config")
        if r.model.n_channels != first.model.n_channels:
            raise ValueError(f"robots of one JAX model must share their regulators, got {first.model.n_channels} "
                             f"and {r.model.n_channels} pressure channels")
    if L < max(len(r.legs) for r in robots):
        raise ValueError(f"n_slots={L} is fewer than a robot's legs")
    data = [_robot_data(r, L, disk.inverse) for r in robots]
    stacked = RobotData(*(np.stack([getattr(d, f.name) for d in data]) for f in dataclasses.fields(RobotData)))
    cfg, mdl = first.config, first.model
    cal = calibration
    floor = bool(floor and mdl.floor is not None)
    if dtype is None:
        dtype = jnp.asarray(0.0).dtype  # float64 under jax_enable_x64, else float32
    single = jnp.dtype(dtype) == jnp.float32
    if delassus is None:
        delassus = "fused16" if single else "dense"
    if cholesky is None:
        cholesky = "kernel" if single else "library"
    settings = Settings(float(cfg.dt), float(mdl.rayleigh_mass), float(mdl.rayleigh_stiffness),
                        tuple(float(g) for g in mdl.gravity), floor, float(mdl.floor.height),
                        float(mdl.floor.contact_distance), float(mdl.floor.friction),
                        int(disk_contacts) if floor else 0, int(leg_contacts) if floor else 0, solver, iterations,
                        (float(cal.a), float(cal.b)), float(rate_kpa_s), int(mdl.n_channels), delassus,
                        cholesky=cholesky)

    def cast(a):
        a = np.asarray(a)
        if a.dtype.kind == "f":
            return jnp.asarray(a, dtype)
        return jnp.asarray(a)

    return Model(jax.tree_util.tree_map(cast, leg), jax.tree_util.tree_map(cast, disk),
                 jax.tree_util.tree_map(cast, stacked), settings)


def select_robots(model: Model, robots) -> Model:
    """The model of a batch made of ``model``'s robots at indices ``robots`` ``(B,)`` (repeats allowed:
    e.g. many copies of a few designs)."""
    pick = jnp.asarray(robots)
    return dataclasses.replace(model, robot=jax.tree_util.tree_map(lambda a: a[pick], model.robot))


#: The engine's precisions by name.
PRECISIONS = {"float32": jnp.float32, "float64": jnp.float64}


def engine_dtype(precision: str):
    """The array dtype of ``precision`` (``"float32"`` or ``"float64"``) for :func:`build_model`.

    Raises:
        ValueError: an unknown precision, or float64 while ``jax_enable_x64`` is off (JAX would
            silently compute in float32; the caller switches it on).
    """
    if precision not in PRECISIONS:
        raise ValueError(f"precision must be one of {sorted(PRECISIONS)}, got {precision!r}")
    if precision == "float64" and not jax.config.jax_enable_x64:
        raise ValueError("the JAX engine in float64 needs jax.config.update('jax_enable_x64', True) first")
    return PRECISIONS[precision]
