"""Design tables of the JAX engine (:mod:`softcrawl.jaxsim.tables`): rows gathered per slot against
the rows of built robots, and the on-disk cache of rested states (round trip, corrupt and
stale entries)."""

import dataclasses

import numpy as np
import pytest

jax = pytest.importorskip("jax")

THREE, FOUR = (1, 0, 0, 2, 2, 0, 0, 0), (1, 0, 2, 0, 1, 0, 3, 0)


@pytest.fixture(scope="module", autouse=True)
def _x64(x64):
    """float64 for the module (the caller's setting restored after)."""


@pytest.fixture(scope="module")
def config():
    """The reduced paper robot with the 25 mm floating disk (the smoke preset's)."""
    from softcrawl.robot import RobotConfig

    return RobotConfig(model="reduced", disk_mesh_size=25.0)


@pytest.fixture(scope="module")
def table(config):
    from softcrawl.design.space import DEFAULT_SPACE
    from softcrawl.jaxsim.tables import build_table

    return build_table(DEFAULT_SPACE, config, floor=False)


def random_designs(space, n, seed):
    rng = np.random.default_rng(seed)
    return [space.raw_designs[i] for i in rng.choice(len(space.raw_designs), n, replace=False)]


def assert_rows_of_built_robots(table, designs, build, n_slots):
    """``table.rows(designs)`` equals :func:`_robot_data` of each built robot (``build(design)``)
    with ``n_slots`` slots: the masks, channels, nodes, placements and weights exactly (the same
    numbers, gathered); the Gram blocks are the same einsum of the same float64 ``A_0^-1``
    entries per point pair (measured bit-identical), within 1e-13 relative in case einsum sums
    another output shape in another order."""
    from softcrawl.jaxsim.model import _robot_data, disk_inverse

    rows = table.rows(designs, n_slots)
    inverse = None
    for b, design in enumerate(designs):
        robot = build(design)
        inverse = disk_inverse(robot) if inverse is None else inverse
        ref = _robot_data(robot, n_slots, inverse)
        for f in dataclasses.fields(ref):
            got, want = getattr(rows, f.name)[b], getattr(ref, f.name)
            assert got.dtype == want.dtype and got.shape == want.shape, f.name
            rtol = 1e-13 if f.name == "att_gram" else 0.0
            np.testing.assert_allclose(got, want, rtol=rtol, atol=0, err_msg=f"{design} {f.name}")
    return rows


def test_rows_are_the_rows_of_built_robots(table, config):
    """20 random designs of the paper's space (3 to 6 legs) in 6 slots, and the 3-legged ones in
    3, against ``build_robot``; absent legs are padded as ``build_model`` pads them."""
    from softcrawl.design.space import DEFAULT_SPACE
    from softcrawl.robot import build_robot

    designs = random_designs(DEFAULT_SPACE, 20, 0)
    assert {sum(v > 0 for v in d) for d in designs} == {3, 4, 5, 6}
    rows = assert_rows_of_built_robots(table, designs, lambda d: build_robot(d, config), 6)
    legs = np.array([sum(v > 0 for v in d) for d in designs])
    np.testing.assert_array_equal(rows.leg_mask, np.arange(6) < legs[:, None])
    absent = ~rows.leg_mask
    assert np.all(rows.rotation[absent] == np.eye(3)) and not rows.translation[absent].any()
    assert not rows.channel[absent].any() and not rows.disk_nodes[absent].any() and not rows.disk_weights[absent].any()
    used = np.repeat(rows.leg_mask, 4, axis=1)
    assert not rows.att_gram[~(used[:, :, None] & used[:, None, :])].any()
    three = [d for d in designs if sum(v > 0 for v in d) == 3] + [THREE]
    assert_rows_of_built_robots(table, three, lambda d: build_robot(d, config), 3)


def test_rows_of_the_hex6_space():
    """The shipped ``hex6`` space (6 slots, 2 regulators, its own leg): 20 random designs."""
    from softcrawl.design.spacefile import load_space, shipped_space_path
    from softcrawl.jaxsim.tables import build_table
    from softcrawl.robot import RobotConfig, build_robot

    space = load_space(shipped_space_path("hex6"))
    config = RobotConfig.for_space(space, model="reduced", disk_mesh_size=25.0)
    table = build_table(space, config)
    assert table.n_slots == 4 and table.att_gram.shape == (24, 24, 3, 3)
    assert_rows_of_built_robots(table, random_designs(space, 20, 1), lambda d: build_robot(d, config, space=space), 4)


def test_float32_rows_are_build_models(config):
    """In float32 the rows are ``build_model``'s (both round the float64 numbers once)."""
    import jax.numpy as jnp

    from softcrawl.design.space import DEFAULT_SPACE
    from softcrawl.jaxsim.model import build_model
    from softcrawl.jaxsim.tables import build_table
    from softcrawl.robot import build_robot

    table = build_table(DEFAULT_SPACE, config, dtype=jnp.float32)
    assert table.dtype == np.float32 and table.parts.disk.inverse.dtype == jnp.float32
    rows = table.rows([THREE, FOUR])
    for b, design in enumerate((THREE, FOUR)):
        ref = build_model([build_robot(design, config)], n_slots=6, dtype=jnp.float32).robot
        for f in dataclasses.fields(ref):
            got, want = getattr(rows, f.name)[b], np.asarray(getattr(ref, f.name))[0]
            assert got.dtype == want.dtype, f.name
            np.testing.assert_allclose(got, want, rtol=1.2e-7 if f.name == "att_gram" else 0, atol=0, err_msg=f.name)


def test_rows_take_arrays_and_strings_and_refuse_bad_designs(table):
    from softcrawl.design.spacefile import InvalidDesignError

    as_tuples = table.rows([THREE, FOUR])
    for other in (table.rows(np.array([THREE, FOUR], np.int8)), table.rows(["1,0,0,2,2,0,0,0", "1 0 2 0 1 0 3 0"])):
        for a, b in zip(dataclasses.astuple(as_tuples), dataclasses.astuple(other)):
            np.testing.assert_array_equal(a, b)
    assert table.rows(np.zeros((0, 8), int)).att_gram.shape == (0, 24, 24, 3, 3)
    with pytest.raises(ValueError, match="a design with 4 legs does not fit the JAX batch's 3 leg slots"):
        table.rows([THREE, FOUR], n_slots=3)
    with pytest.raises(InvalidDesignError, match="slot 2: value 4 not in"):
        table.rows([THREE, (1, 0, 4, 0, 1, 0, 3, 0)])
    with pytest.raises(InvalidDesignError, match="too few legs: 2"):
        table.rows(np.array([[1, 0, 0, 0, 1, 0, 0, 0]]))
    with pytest.raises(InvalidDesignError, match="must have 8 slots"):
        table.rows([(1, 0, 1)])


def test_build_table_refuses_what_the_engine_cannot_step(config):
    """A full-order robot (the JAX engine's error); a config and a factory at once; a factory that
    places a slot's leg differently depending on the other slots."""
    from softcrawl.design.space import DEFAULT_SPACE
    from softcrawl.jaxsim.tables import build_table, covering_designs
    from softcrawl.robot import RobotConfig, build_robot

    assert covering_designs(DEFAULT_SPACE) == [(1, 1, 1, 1, 1, 1, 0, 0), (1, 0, 0, 0, 0, 0, 1, 1)]
    with pytest.raises(ValueError, match="reduced robots with a floating-frame disk"):
        build_table(DEFAULT_SPACE, RobotConfig(leg_mesh_size=12.0, disk_mesh_size=25.0))
    with pytest.raises(ValueError, match="not both"):
        build_table(DEFAULT_SPACE, config, factory=lambda d: build_robot(d, config))
    turned = dataclasses.replace(DEFAULT_SPACE, slot_angles_deg=tuple(a + 5.0 for a in DEFAULT_SPACE.slot_angles_deg))

    def factory(design):  # the second covering design's legs turned by 5 degrees
        return build_robot(design, config, space=turned if sum(design) == 3 else DEFAULT_SPACE)

    with pytest.raises(ValueError, match="places slot 0's leg differently"):
        build_table(DEFAULT_SPACE, factory=factory)


# -- settled states ---------------------------------------------------------------------------------
#: Three steps of settling (the cache's behaviour does not depend on the rule; a short one compiles
#: and runs fast).
SHORT = dict(max_seconds=0.03)


def states(table, folder, **settling):
    from softcrawl.jaxsim.tables import SettledStates
    from softcrawl.robot import Settling

    return SettledStates(table, Settling(**{**SHORT, **settling}), folder)


def same_states(a, b):
    la, ta = jax.tree_util.tree_flatten(a.state)
    lb, tb = jax.tree_util.tree_flatten(b.state)
    assert ta == tb and (a.steps, a.speed, a.ok) == (b.steps, b.speed, b.ok)
    for x, y in zip(la, lb):
        assert x.dtype == y.dtype and x.shape == y.shape
        np.testing.assert_array_equal(x, y)


@pytest.fixture(scope="module")
def settled(table, tmp_path_factory):
    """THREE and FOUR settled in 4 slots into a fresh folder: ``(folder, [Rested] * 2)``."""
    folder = tmp_path_factory.mktemp("settled")
    cache = states(table, folder)
    rested = cache.get([THREE, FOUR], 4)
    assert cache.settled == 2 and cache.loaded == 0
    return folder, rested


def test_settled_states_round_trip(table, settled, recwarn):
    """A second cache object on the folder reads both designs (nothing settled), bit for bit and
    with the state's structure; what was stored is each design's row of the engine's settle of
    the batch (:func:`make_batch_settle`, compiled once per rule)."""
    from softcrawl.jaxsim.batch import take
    from softcrawl.jaxsim.tables import Rested, _settler

    folder, rested = settled
    cache = states(table, folder)
    again = cache.get([FOUR, THREE, FOUR], 4)
    assert cache.settled == 0 and cache.loaded == 3 and not recwarn.list
    for a, b in zip(again, [rested[1], rested[0], rested[1]]):
        same_states(a, b)
    assert cache.rule == (0.5, 5, 3) and rested[0].steps == 3 and rested[0].ok and rested[0].state.q.shape[0] == 4
    state, steps, speed, ok = jax.device_get(_settler(*cache.rule)(table.model([FOUR, THREE, THREE, THREE], 4)))
    for j, b in ((0, 1), (1, 0)):
        same_states(Rested(take(state, j), int(steps[j]), float(speed[j]), bool(ok[j])), rested[b])


def test_settling_halves_its_batch_where_the_device_runs_out_of_memory(table, tmp_path):
    """Three designs at a batch of 4, on a device (faked) that holds 2 robots: the batch of 4 runs
    out of memory, the cache warns, settles 2 and then 1 (padded to 2) and remembers the batch
    (``largest_batch``); every state is, to the bit, what a cache settling 2 at a time gives."""
    OTHER = (0, 1, 0, 3, 2, 0, 0, 0)
    cache = states(table, tmp_path / "a")
    real, sizes = cache._settle, []

    def settle(model):
        sizes.append(model.robot.leg_mask.shape[0])
        if sizes[-1] > 2:
            raise jax.errors.JaxRuntimeError("RESOURCE_EXHAUSTED: Out of memory while trying to allocate 64 bytes.")
        return real(model)

    cache._settle = settle
    with pytest.warns(UserWarning, match="out of memory on settling of 4 robots a batch; going on at 2"):
        got = cache.get([THREE, FOUR, OTHER], 4, batch=4)
    assert sizes == [4, 2, 2] and cache.largest_batch == 2 and cache.settled == 3
    want = states(table, tmp_path / "b").get([THREE, FOUR, OTHER], 4, batch=2)
    for a, b in zip(got, want):
        same_states(a, b)


def copy_folder(folder, tmp_path):
    import shutil

    return shutil.copytree(folder, tmp_path / "copy")


def entry(cache, design, n_slots=4):
    return cache._path(cache.key(n_slots), design)


@pytest.mark.parametrize("damage", ["garbage", "changed state", "other design"])
def test_a_bad_entry_is_settled_again_with_one_warning(table, settled, tmp_path, damage):
    """A file that is not an npz, one whose state was changed (its SHA-256 no longer matches),
    and another design's file in this design's place: each is settled again with one warning
    line, rewritten, and read back without a warning."""
    folder, rested = settled
    cache = states(table, copy_folder(folder, tmp_path))
    path = entry(cache, THREE)
    if damage == "garbage":
        path.write_bytes(b"not a zip file")
    elif damage == "changed state":
        with np.load(path) as z:
            arrays = dict(z)
        arrays["state"] = arrays["state"][::-1].copy()
        np.savez(path, **arrays)
    else:
        path.write_bytes(entry(cache, FOUR).read_bytes())
    with pytest.warns(UserWarning, match="settled-state cache entry .* is unusable") as caught:
        got = cache.get([THREE, FOUR], 4)
    assert len(caught) == 1 and cache.settled == 1 and cache.loaded == 1
    same_states(got[0], rested[0])
    fresh = states(table, cache.folder)
    same_states(fresh.get([THREE], 4)[0], rested[0])
    assert fresh.loaded == 1 and fresh.settled == 0


def test_stale_keys_are_not_used(table, settled, tmp_path, monkeypatch):
    """Another engine version, other settings, another rest rule, another precision or other
    leg slots give another key (folder): the stored states are not read."""
    import jax.numpy as jnp

    from softcrawl.jaxsim import engine

    folder, rested = settled
    cache = states(table, copy_folder(folder, tmp_path))
    key = cache.key(4)
    assert len({key, cache.key(5), states(table, folder, max_seconds=0.04).key(4)}) == 3
    swept = dataclasses.replace(table, parts=dataclasses.replace(
        table.parts, settings=dataclasses.replace(table.parts.settings, iterations=99)))
    single = dataclasses.replace(table, parts=jax.tree_util.tree_map(lambda a: a.astype(jnp.float32), table.parts))
    assert states(swept, folder).key(4) != key and states(single, folder).key(4) != key
    monkeypatch.setattr(engine, "ENGINE_VERSION", engine.ENGINE_VERSION + 1)
    bumped = states(table, cache.folder)
    assert bumped.key(4) != key
    same_states(bumped.get([THREE], 4)[0], rested[0])
    assert bumped.settled == 1 and bumped.loaded == 0


def test_prebuild_settles_what_is_missing(table, settled, tmp_path):
    """``prebuild`` settles the designs the folder lacks (in leg-count order) and none the second time."""
    folder, _ = settled
    cache = states(table, copy_folder(folder, tmp_path))
    designs = [FOUR, (1, 1, 0, 0, 2, 0, 0, 0), THREE]
    assert cache.prebuild(designs, 4, progress=False) == 1 and cache.loaded == 2
    assert cache.prebuild(designs, 4, progress=False) == 0 and cache.loaded == 5


def test_the_evaluator_settles_a_design_once_per_machine(config, tmp_path):
    """:class:`JaxEvaluator` reads the rested states another evaluator settled into the same
    folder (nothing settled again), and its episodes start from them."""
    from softcrawl.jaxsim.episodes import JaxEvaluator
    from softcrawl.robot import Settling

    first, second = (JaxEvaluator(config, "float64", Settling(**SHORT), settled_folder=tmp_path) for _ in range(2))
    first.prepare([THREE])
    second.prepare([THREE, THREE])
    assert (first.states.settled, first.states.loaded, second.states.settled, second.states.loaded) == (1, 0, 0, 1)
    assert first.settles == second.settles == 1
    a, b = first.settled(THREE), second.settled(THREE)
    assert (a.legs, a.steps, a.at_rest, a.diverged, a.start_x) == (b.legs, b.steps, b.at_rest, b.diverged, b.start_x)
    np.testing.assert_array_equal(a.state.x, b.state.x)
