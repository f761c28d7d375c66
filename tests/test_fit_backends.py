"""The three solver backends (jaxrefl/fit/_backends.py) on the shared problem zoo: lean,
optimistix and jaxopt reach the same optimum on well-posed pixels, and jaxopt's
deprecation warnings never reach the user."""

from __future__ import annotations

import subprocess
import sys
import textwrap
import warnings

import jax.numpy as jnp
import numpy as np
import pytest
from fit_zoo import problem_zoo

import jaxrefl
from jaxrefl import fit

ZOO = {p.name: p for p in problem_zoo()}
# Library solvers for the comparison: tolerances tight enough that their own stopping error
# is far below the agreement tolerances (float64).
SOLVERS = {
    "lean": fit.LMOptions(),
    "optimistix": fit.OptimistixLM(rtol=1e-10, atol=1e-12),
    "jaxopt": fit.JaxoptLM(rtol=1e-10, atol=1e-12),
}


def _solve(pr, backend):
    space = fit.ParamSpace(pr.model)
    res = fit.make_residual(pr.model, space)
    theta0 = fit.initial_theta(res, pr.data)
    theta, info = fit.solve(res, theta0, pr.data, SOLVERS[backend], space=space)
    assert theta.shape == theta0.shape and info.status.shape == theta0.shape[:1]
    return np.asarray(space.natural_vector(theta)), np.asarray(info.cost), info


@pytest.mark.slow
@pytest.mark.parametrize("name", list(ZOO))
def test_backends_agree_on_the_zoo(name):
    """Same optimum on >= 99% of the well-posed pixels: natural parameters within 1e-4
    relative (exact problems: every solver stops far below that, and a well-posed pixel's
    parameters are determined by its data), or final costs within 1e-6 relative (noisy
    problems, where a flat direction may leave parameters less settled than the cost)."""
    pr = ZOO[name]
    x_lean, c_lean, info = _solve(pr, "lean")
    assert np.all(np.isin(np.asarray(info.status)[pr.well_posed], [0, 1]))
    for backend in ("optimistix", "jaxopt"):
        x, c, _ = _solve(pr, backend)
        same_x = np.max(np.abs(x - x_lean) / np.abs(x_lean), axis=1) < 1e-4
        same_c = np.abs(c - c_lean) <= 1e-6 * np.maximum(c, c_lean)
        agree = (same_x | same_c)[pr.well_posed]
        assert agree.mean() >= 0.99, (backend, np.flatnonzero(~agree))
        if not pr.noisy:  # exact data: every backend fits the well-posed pixels exactly
            assert np.all(c[pr.well_posed] < 1e-12 * np.max(c_lean + 1.0))


def test_jaxopt_warnings_do_not_leak():
    pr = ZOO["lambert"]
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        r = fit.fit_pixels(pr.model, pr.data, config=fit.FitConfig(solver=fit.JaxoptLM()))
    assert r.backend == "jaxopt"
    assert r.status_counts()["CONVERGED"] == pr.data.obs.shape[0]
    # In a fresh interpreter (where jaxopt's import-time DeprecationWarning fires) with every
    # warning turned into an error.
    code = textwrap.dedent(
        """
        import jax.numpy as jnp, jaxrefl
        from jaxrefl import fit
        m = jaxrefl.brdf.get("lambert")
        wi = jnp.tile(jnp.asarray([0.0, 0.6, 0.8]), (4, 5, 1))
        data = fit.pixel_data(jnp.full((4, 5, 1), 0.1), wi, scale=jnp.pi)
        r = fit.fit_pixels(m, data, config=fit.FitConfig(solver=fit.JaxoptLM()))
        assert int((r.status == 0).sum()) == 4, r.status
        """
    )
    out = subprocess.run(
        [sys.executable, "-W", "error", "-c", code], capture_output=True, text=True, timeout=300
    )
    assert out.returncode == 0, out.stderr[-3000:]


def test_backend_errors_and_outputs():
    pr = ZOO["lambert"]
    space = fit.ParamSpace(pr.model)
    res = fit.make_residual(pr.model, space)
    with pytest.raises(TypeError, match="solver must be"):
        fit.solve(res, jnp.zeros((4, 3)), pr.data, "scipy")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match=r"\(N, P\)"):
        fit.solve(res, jnp.zeros(3), pr.data)
    # optimistix maps its result codes; a NaN start becomes NONFINITE_INPUT, nothing crashes.
    # The settings of the zoo comparison (``_solve``: 256 steps, SOLVERS), so the solver
    # compiled for test_backends_agree_on_the_zoo[lambert] is reused.
    theta0 = fit.initial_theta(res, pr.data).at[0].set(jnp.nan)
    solver = SOLVERS["optimistix"]
    steps = solver.max_iters
    assert steps == 256
    _, info = fit.solve(res, theta0, pr.data, solver, space=space)
    st = np.asarray(info.status)
    assert st[0] == fit.Status.NONFINITE_INPUT and np.all(st[1:] == fit.Status.CONVERGED)
    assert np.all(np.asarray(info.iterations[1:]) <= steps)


@pytest.mark.parametrize(
    ("package", "solver"), [("jaxopt", "JaxoptLM"), ("optimistix", "OptimistixLM")]
)
def test_missing_backend_gives_an_actionable_error(monkeypatch, package, solver):
    """optimistix and jaxopt are optional (the ``backends`` extra): their solvers say so."""
    import builtins

    real_import = builtins.__import__

    def fake_import(name, *args, **kwargs):
        if name == package or name.startswith(f"{package}."):
            raise ImportError(f"No module named '{package}'")
        return real_import(name, *args, **kwargs)

    monkeypatch.delitem(sys.modules, package, raising=False)
    monkeypatch.setattr(builtins, "__import__", fake_import)
    m = jaxrefl.brdf.get("lambert")
    res = fit.make_residual(m, fit.ParamSpace(m, channels=1))
    data = fit.pixel_data(jnp.ones((2, 3, 1)), jnp.tile(jnp.asarray([0.0, 0.0, 1.0]), (2, 3, 1)))
    with pytest.raises(ImportError, match=rf"{solver} needs .*pip install 'jaxrefl\[backends\]'"):
        fit.solve(res, jnp.zeros((2, 1)), data, getattr(fit, solver)())


def test_optimistix_on_float32_data_under_x64():
    """The suite runs with jax_enable_x64: optimistix's float64 damping term would make
    lineax refuse a float32 system. float32 in gives float32 out and the lean optimum."""
    m = jaxrefl.brdf.get("lambert")
    rng = np.random.default_rng(0)
    wi = rng.normal(size=(3, 8, 3)) * [1, 1, 0] + [0, 0, 2.0]
    wi /= np.linalg.norm(wi, axis=-1, keepdims=True)
    obs = rng.uniform(0.05, 0.2, (3, 8, 3))
    d = fit.pixel_data(jnp.asarray(obs, jnp.float32), jnp.asarray(wi, jnp.float32))
    r = fit.fit_pixels(m, d, config=fit.FitConfig(solver=fit.OptimistixLM()))
    lean = fit.fit_pixels(m, d)
    assert r.theta.dtype == jnp.float32 and r.cost.dtype == jnp.float32
    assert (np.asarray(r.status) <= fit.Status.AT_BOUND).all()
    np.testing.assert_allclose(r.params["albedo"], lean.params["albedo"], rtol=1e-3)


def test_solver_objects_carry_their_budget_and_write_json():
    """Each solver carries its own iteration budget; ``max_iters`` of a library solver
    bounds the iterations it reports, and every option object names itself in JSON."""
    pr = ZOO["lambert"]
    space = fit.ParamSpace(pr.model)
    res = fit.make_residual(pr.model, space)
    theta0 = jnp.broadcast_to(space.default_theta(jnp.float64), (pr.data.obs.shape[0], space.size))
    _, info = fit.solve(res, theta0, pr.data, fit.LMOptions(max_iters=2), space=space)
    assert int(np.max(np.asarray(info.iterations))) <= 2
    assert fit.OptimistixLM().max_iters == fit.JaxoptLM().max_iters == 256
    assert fit.LMOptions().max_iters == 40
    with pytest.raises(ValueError, match="max_iters"):
        fit.OptimistixLM(max_iters=0)
    assert fit.OptimistixLM(max_iters=9).to_json() == {
        "type": "optimistix",
        "max_iters": 9,
        "rtol": None,
        "atol": None,
        "cond_max": None,
        "bound_rtol": 1e-3,
    }
    cfg = fit.FitConfig(
        solver=fit.JaxoptLM(), noise=fit.ShotNoise(read=0.002, gain=0.002), loss=fit.Huber(2.0)
    )
    js = cfg.to_json()
    assert js["noise"] == {"type": "shot", "read": 0.002, "gain": 0.002}
    assert js["loss"] == {"type": "huber", "delta": 2.0} and js["solver"]["type"] == "jaxopt"
    assert js["dtype"] is None
    assert fit.FitConfig(dtype=jnp.float32).dtype == np.dtype(np.float32)
    assert fit.FitConfig(dtype=jnp.float32).to_json()["dtype"] == "float32"
    with pytest.raises(ValueError, match="floating"):
        fit.FitConfig(dtype=np.int32)
