"""A sensor small enough to integrate exactly: two or more slots on a line (state ``[u]``,
D = 1), labelled Gaussian measurements, a field of view and a data-driven density near the
measurements (the invariance tests of the multitarget prior's terms, issue 22)."""

import math

import torch

from torchmcmcpf.models.base import SensorModel

DT = torch.float64
FOV = (-10.0, 10.0)
R, Q, SPREAD, P_U = 2.0, 1.0, 1.0, 0.1


class LineSensor(SensorModel):
    """``z (B, K, 1)``: ``z_j = u_j + N(0, R)`` per slot (an absent slot contributes
    nothing); resolution 1; data-driven density
    ``g(u) = P_U U(FOV) + (1 - P_U) (1/K) sum_j N(u; z_j, SPREAD^2)``; ``p_0 = U(FOV)``.
    """

    def log_likelihood(self, x, z, exists=None):
        zz = z.reshape(z.shape[:1] + (1,) * (x.dim() - 3) + z.shape[1:])
        terms = (-0.5 * (x - zz).square() / R).sum(-1)  # (B, *S, K)
        return (terms if exists is None else torch.where(exists, terms, 0.0)).sum(-1)

    def resolution_coords(self, x):
        return x[..., :1]

    def place(self, x, coords):
        return torch.cat([coords, x[..., 1:]], -1)

    @staticmethod
    def log_g(u, z):
        """``log g(u)`` for ``u (B, *S)``, ``z (B, K, 1)``."""
        zz = z[..., 0].reshape(z.shape[:1] + (1,) * (u.dim() - 1) + (z.shape[1],))
        log_n = -0.5 * ((u.unsqueeze(-1) - zz) / SPREAD).square() - math.log(SPREAD * math.sqrt(2 * math.pi))
        near = torch.logsumexp(log_n, -1) - math.log(z.shape[1])
        log_u = -math.log(FOV[1] - FOV[0])
        return torch.logaddexp(torch.full_like(near, math.log(P_U) + log_u), math.log1p(-P_U) + near)

    def sample_from_data(self, z, shape, *, generator, dtype=torch.float32, scored=None):
        b, k = z.shape[:2]
        q = math.prod(shape[1:])
        pick = torch.randint(k, (b, q), generator=generator)
        near = torch.take_along_dim(z[..., 0], pick, 1) + SPREAD * torch.randn(b, q, generator=generator, dtype=DT)
        flat = FOV[0] + (FOV[1] - FOV[0]) * torch.rand(b, q, generator=generator, dtype=DT)
        u = torch.where(torch.rand(b, q, generator=generator, dtype=DT) < P_U, flat, near)
        inside = (u >= FOV[0]) & (u <= FOV[1])
        log_ratio = torch.where(inside, -math.log(FOV[1] - FOV[0]) - self.log_g(u, z), -math.inf).reshape(tuple(shape))
        if scored is not None:  # the protocol: 0 where no move reads the ratio
            log_ratio = torch.where(scored, log_ratio, 0.0)
        return u.reshape(tuple(shape) + (1,)).to(dtype), log_ratio.to(dtype)


def log_fov(u):
    """``log p_0(u)``: uniform over the field of view."""
    inside = (u >= FOV[0]) & (u <= FOV[1])
    return torch.where(inside, -math.log(FOV[1] - FOV[0]), -math.inf)
