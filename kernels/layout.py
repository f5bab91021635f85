"""Record layouts shared by the kernels and their Python decoders, defined once.

``Rec``: the per-Gaussian record the projection kernel writes (``packed [B, N, Rec.SIZE]``) and both blend
layouts read. ``Cam``: the per-pose camera record the projection writes (``cams [B, Cam.SIZE]``) and reads, and
the derivative pass reads. ``Stat``: the per-pose photometric statistics the fused cost kernels accumulate
(``stats [B, Stat.SIZE]``) and ``hgsloc_plugin.core.costs`` decodes. Kernels index with these names inside
``ti.static`` code, so a field moves in one place only.
"""


class Rec:
    """Per-Gaussian record after projection (float32)."""

    X = 0  # 2D mean, pixels
    Y = 1
    CA = 2  # conic (a, b, c): sigma = 0.5 (a dx^2 + c dy^2) + b dx dy
    CB = 3
    CC = 4
    OPACITY = 5
    LIM = 6  # ln(opacity / alpha_min): alpha >= alpha_min  <=>  sigma <= LIM
    RY = 7  # y half-extent of the ellipse sigma <= LIM (+ 0.01 margin)
    RGB = 8  # 8, 9, 10: colour after SH and the +0.5 offset, clamped at 0
    DEPTH = 11  # camera z
    SIZE = 12


class Cam:
    """Per-pose camera record (float32), from the pose's intrinsics and extent coefficients."""

    FX = 0  # intrinsics, pixels
    FY = 1
    CX = 2
    CY = 3
    LIM_X_POS = 4  # Jacobian clamps of x / z and y / z (``projection.jacobian_clamps``)
    LIM_X_NEG = 5
    LIM_Y_POS = 6
    LIM_Y_NEG = 7
    EARLY_A = 8  # early frustum test: box half-extent <= EARLY_A * smax / z + EARLY_B (normalised units)
    EARLY_B = 9
    X_LO = 10  # the image's bounds in normalised units (x / z, y / z)
    X_HI = 11
    Y_LO = 12
    Y_HI = 13
    DILATION = 14  # pixels^2 added to the projected covariance's diagonal (``RasterConfig.widening``)
    FILTER = 15  # pixels^2 added after it, the opacity compensated (0: none)
    SIZE = 16


class Stat:
    """Per-pose statistics of a rendering r against the query q over the valid pixels (float64 totals)."""

    N = 0  # valid pixels
    SAD = 1  # sum |r - q| over RGB
    SSD = 2  # sum (r - q)^2 over RGB
    CHANNELS = 3  # then, per channel c, 5 sums starting at CHANNELS + PER_CHANNEL * c:
    SR = 0  # sum r
    SQ = 1  # sum q
    SRR = 2  # sum r^2
    SQQ = 3  # sum q^2
    SRQ = 4  # sum r q
    PER_CHANNEL = 5
    SIZE = CHANNELS + 3 * PER_CHANNEL

    @staticmethod
    def at(channel: int, field: int) -> int:
        """Offset of ``field`` (SR ... SRQ) of ``channel`` (0, 1, 2)."""
        return Stat.CHANNELS + Stat.PER_CHANNEL * channel + field
