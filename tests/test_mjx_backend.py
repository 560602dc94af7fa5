"""The mjx backend on MuJoCo Warp (`impl="warp"`): contacts read through Warp's shared buffer agree with MJX's JAX
implementation, and a settled reset agrees with C MuJoCo. Warp runs on the CPU too (slowly), so these run wherever
warp-lang is installed (`pip install .[warp]`) and skip elsewhere."""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from mujoco import mjx

from partinstruct_mjx.sim import mjx_backend
from partinstruct_mjx.sim.mujoco_backend import MujocoBackend

pytestmark = pytest.mark.slow

XY = np.array([[0.05, 0.10], [-0.05, 0.15]])


@pytest.fixture(autouse=True)
def warp_installed():
    from mujoco.mjx import warp as mjx_warp

    if not mjx_warp.WARP_INSTALLED:
        pytest.skip("warp-lang is not installed (pip install .[warp])")


def test_warp_contacts_match_the_jax_implementation(scene):
    with MujocoBackend(scene, len(XY)) as backend:
        backend.reset(XY)
        qpos = np.stack([d.qpos.copy() for d in backend.datas])
    weight = scene.model.body_subtreemass[scene.object_body] * -scene.model.opt.gravity[2]
    for impl in ("jax", "warp"):
        model = mjx.put_model(scene.model, impl=impl)
        fresh = mjx_backend.fresh_data(scene.model, model, len(XY))
        data = jax.jit(jax.vmap(lambda q: mjx.forward(model, fresh.replace(qpos=q))))(jnp.asarray(qpos, jnp.float32))
        geom, _, force = (np.asarray(x) for x in jax.vmap(mjx_backend.contacts)(data))
        for env in range(len(XY)):
            touching = force[env] > 0  # the robot at home touches nothing: the object rests on the table alone
            assert {tuple(sorted(pair)) for pair in geom[env][touching]} <= {
                (min(scene.table_geom, g), max(scene.table_geom, g)) for g in scene.object_geoms}, (impl, env)
            assert force[env].sum() == pytest.approx(weight, rel=0.03), (impl, env)


def test_mjx_backend_settles_like_c_mujoco_on_warp(scene, monkeypatch):
    monkeypatch.setattr(mjx, "put_model", functools.partial(mjx.put_model, impl="warp"))
    backend = mjx_backend.MjxBackend(scene, len(XY))
    assert backend.model.impl == mjx.Impl.WARP
    state = backend.reset(XY)
    with MujocoBackend(scene, len(XY)) as reference:
        expected = reference.reset(XY)
    np.testing.assert_allclose(np.asarray(state.object_pos), np.asarray(expected.object_pos), atol=3e-3)
    np.testing.assert_allclose(np.asarray(state.tcp_pos), np.asarray(expected.tcp_pos), atol=3e-3)
