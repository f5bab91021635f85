"""Spherical-harmonics colour evaluation as a Taichi function (degrees 0-3).

Constants and basis order follow the reference 3DGS / gsplat ``_spherical_harmonics`` (CONVENTIONS §5).
"""


import functools

import taichi as ti

C0 = 0.28209479177387814
C1 = 0.4886025119029199
C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
C3 = (-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154, -0.4570457994644658,
      1.445305721320277, -0.5900435899266435)


@functools.cache
def make_sh_func(degree: int):
    """A ``@ti.func eval_sh(sh [N, K, 3] ndarray, i, dir vec3) -> vec3`` (without the +0.5 offset)."""

    @ti.func
    def eval_sh(sh: ti.template(), i: ti.i32, d: ti.template()) -> ti.math.vec3:
        res = ti.Vector([0.0, 0.0, 0.0])
        for c in ti.static(range(3)):
            res[c] = C0 * sh[i, 0, c]
        if ti.static(degree >= 1):
            x, y, z = d[0], d[1], d[2]
            for c in ti.static(range(3)):
                res[c] += -C1 * y * sh[i, 1, c] + C1 * z * sh[i, 2, c] - C1 * x * sh[i, 3, c]
            if ti.static(degree >= 2):
                xx, yy, zz = x * x, y * y, z * z
                xy, yz, xz = x * y, y * z, x * z
                for c in ti.static(range(3)):
                    res[c] += (C2[0] * xy * sh[i, 4, c] + C2[1] * yz * sh[i, 5, c]
                               + C2[2] * (2.0 * zz - xx - yy) * sh[i, 6, c] + C2[3] * xz * sh[i, 7, c]
                               + C2[4] * (xx - yy) * sh[i, 8, c])
                if ti.static(degree >= 3):
                    for c in ti.static(range(3)):
                        res[c] += (C3[0] * y * (3.0 * xx - yy) * sh[i, 9, c] + C3[1] * xy * z * sh[i, 10, c]
                                   + C3[2] * y * (4.0 * zz - xx - yy) * sh[i, 11, c]
                                   + C3[3] * z * (2.0 * zz - 3.0 * xx - 3.0 * yy) * sh[i, 12, c]
                                   + C3[4] * x * (4.0 * zz - xx - yy) * sh[i, 13, c]
                                   + C3[5] * z * (xx - yy) * sh[i, 14, c]
                                   + C3[6] * x * (xx - 3.0 * yy) * sh[i, 15, c])
        return res

    return eval_sh
