"""Small SDC models with known structure, a sine reference and a closed loop on the model, for
the law tests (shared; no test imports another)."""
import numpy as np

#: rest tip of the test models [m]
REST = np.array([0.01, -0.02, 0.3])


class StiffeningModel:
    """A state-dependent SDC model (AG only): ẍ = −k(1 + (p/p₀)²) p − c v + G₂(p) u, G₂ rotating
    with p."""

    rest_tip = REST

    def AG(self, x):
        x = np.atleast_2d(x)
        n = len(x)
        A = np.zeros((n, 4, 4))
        A[:, 0, 2] = A[:, 1, 3] = 1.0
        s = 1.0 + (x[:, :2] / 5e-3) ** 2
        A[:, 2, 0], A[:, 3, 1] = -300.0 * s[:, 0], -900.0 * s[:, 1]
        A[:, 2, 2] = A[:, 3, 3] = -2.0
        th = 20.0 * x[:, 1]
        G = np.zeros((n, 4, 2))
        G[:, 2, 0], G[:, 2, 1] = 10.0 * np.cos(th), 600.0 + 50.0 * np.sin(th)
        G[:, 3, 0], G[:, 3, 1] = -600.0, 5.0 + 100.0 * x[:, 0]
        return A, G


def sine_reference(t, amp=np.array([2e-3, 4e-3]), w=2 * np.pi * 3.0):
    """p_d = amp sin(ωt) about the rest tip: (pos, vel, acc) (1, 2) each."""
    return (REST[None, :2] + amp * np.sin(w * t), (amp * w * np.cos(w * t))[None],
            (-amp * w * w * np.sin(w * t))[None])


def track_sine(law, model, seconds=0.3, dt=2e-4) -> float:
    """Integrate the model's plant (RK4, u held over dt) under ``law`` from the start of
    :func:`sine_reference`: the largest tip error [m] over the run."""
    p, v, _ = sine_reference(0.0)
    x = np.concatenate([p[0] - REST[:2], v[0]])
    err = []
    for k in range(int(round(seconds / dt))):
        p_d, v_d, a_d = sine_reference(k * dt)
        u = law.compute(x[None, :2] + REST[:2], x[None, 2:], p_d, v_d, ref_acc=a_d).u[0]

        def f(z):
            A, G = model.AG(z)
            return A[0] @ z + G[0] @ u
        k1 = f(x)
        k2 = f(x + dt / 2 * k1)
        k3 = f(x + dt / 2 * k2)
        x = x + dt / 6 * (k1 + 2 * k2 + 2 * k3 + f(x + dt * k3))
        err.append(np.linalg.norm(x[:2] + REST[:2] - sine_reference((k + 1) * dt)[0][0]))
    return float(np.max(err))
