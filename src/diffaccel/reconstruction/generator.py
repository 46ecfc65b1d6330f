"""Neural beam generator: Gaussian base samples -> MLP -> particles in Bmad units."""

from __future__ import annotations

import math

import torch
from torch import Tensor, nn

#: Particles per block when :meth:`BeamGenerator.forward` samples without
#: gradients (blocks of the MLP's hidden activations fit in the CPU's cache).
_SAMPLE_CHUNK = 16_384


class BeamGenerator(nn.Module):
    """Generative model of a beam's phase-space distribution.

    A ``dims``-dimensional standard-normal base sample ``u`` is mapped to
    particles by ``x = s0 * (b + exp(a) * (L u + Q q(u) + f(u)))`` where ``s0``
    is the fixed reference scale (the initial ``scale``), ``b`` the learnable
    offset and ``exp(a)`` the learnable scale, both in units of ``s0`` (so that
    every trainable number is of order one and one learning rate suits all),
    ``L`` a learnable ``dims x dims`` mixing matrix (initialised from a guessed
    correlation matrix) and ``f`` a tanh MLP whose last layer starts at zero (so
    the initial beam is the Gaussian ``offset, scale, L``). Every call draws
    *fresh* base samples: a fixed sample over-fits its own shot noise.

    In 6D a learnable ``6 x 21`` matrix ``Q`` (starting at zero) also weighs the
    second-order products ``q(u)`` of the base (:func:`quadratic_features`).
    The tanh MLP is bounded, so without it a coordinate that grows with the
    square of another (the energy of a curved chirp, ``pz ~ c z^2``) has its
    tails cut where ``f`` saturates: the tips of the chirp's curve go missing
    from the dipole-screen images, and on strongly curved beams rms pz comes
    out 3-4 % low. 4D generators
    have no ``Q``; 6D runs saved before it load with ``Q = 0``.

    Args:
        dims: 6 for the full phase space, 4 for transverse only (``z = pz = 0``).
        width: Hidden-layer width of the MLP.
        depth: Number of hidden layers of the MLP (>= 1).
        scale: Initial rms scale of each generated coordinate, Bmad units
            ([m], [1], [m], [1], [m], [1]); shape ``(dims,)``.
        offset: Initial centroid, same units and shape as ``scale``; zeros if None.
        correlation: Initial correlation matrix ``(dims, dims)``; identity if None.
        generator: ``torch.Generator`` used to initialise the weights
            (deterministic for a seed).

    Shapes:
        ``forward(n)`` returns ``(n, 6)`` particles in Bmad coordinates
        ``(x, px, y, py, z, pz)``; with ``dims = 4`` the last two columns are 0.

    Raises:
        ValueError: for ``dims`` other than 4 or 6, non-positive sizes or scales.

    Example:
        >>> g = torch.Generator().manual_seed(0)
        >>> gen = BeamGenerator(4, scale=torch.tensor([1e-3, 1e-4, 1e-3, 1e-4]),
        ...                     generator=g)
        >>> gen(1000, generator=g).shape
        torch.Size([1000, 6])
    """

    def __init__(
        self,
        dims: int,
        *,
        width: int = 64,
        depth: int = 2,
        scale: Tensor,
        offset: Tensor | None = None,
        correlation: Tensor | None = None,
        generator: torch.Generator | None = None,
    ) -> None:
        super().__init__()
        if dims not in (4, 6):
            raise ValueError(f"dims must be 4 or 6; got {dims}.")
        if width < 1 or depth < 1:
            raise ValueError(f"width and depth must be >= 1; got {width}, {depth}.")
        scale = torch.as_tensor(scale, dtype=torch.get_default_dtype())
        if scale.shape != (dims,):
            raise ValueError(
                f"scale must have shape ({dims},); got {tuple(scale.shape)}."
            )
        if not torch.isfinite(scale).all() or (scale <= 0).any():
            raise ValueError(f"scale must be finite and > 0; got {scale.tolist()}.")
        self.dims = dims
        self.width = width
        self.depth = depth
        self.register_buffer("ref_scale", scale.clone())
        self.log_scale = nn.Parameter(torch.zeros_like(scale))
        off = torch.zeros(dims) if offset is None else torch.as_tensor(offset)
        self.offset = nn.Parameter(off.to(scale.dtype) / scale)
        corr = torch.eye(dims) if correlation is None else torch.as_tensor(correlation)
        chol = torch.linalg.cholesky(
            corr.to(torch.float64) + 1e-9 * torch.eye(dims, dtype=torch.float64)
        )
        self.mix = nn.Parameter(chol.to(scale.dtype))
        layers: list[nn.Module] = [nn.Linear(dims, width), nn.Tanh()]
        for _ in range(depth - 1):
            layers += [nn.Linear(width, width), nn.Tanh()]
        layers.append(nn.Linear(width, dims))
        self.mlp = nn.Sequential(*layers)
        self._init_weights(generator)
        if dims == 6:
            n_products = dims * (dims + 1) // 2
            self.quad = nn.Parameter(torch.zeros(dims, n_products, dtype=scale.dtype))

    def _load_from_state_dict(  # type: ignore[override]
        self, state_dict: dict, prefix: str, *args: object, **kwargs: object
    ) -> None:
        key = prefix + "quad"
        if self.dims == 6 and key not in state_dict:
            # a 6D generator saved before the quadratic term: Q = 0 is the same beam
            state_dict[key] = torch.zeros_like(self.quad)
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)

    def _init_weights(self, generator: torch.Generator | None) -> None:
        linears = [m for m in self.mlp if isinstance(m, nn.Linear)]
        with torch.no_grad():
            for lin in linears[:-1]:
                bound = 1.0 / math.sqrt(lin.in_features)
                lin.weight.uniform_(-bound, bound, generator=generator)
                lin.bias.uniform_(-bound, bound, generator=generator)
            linears[-1].weight.zero_()
            linears[-1].bias.zero_()

    @property
    def scale(self) -> Tensor:
        """Per-coordinate scale, shape ``(dims,)``, Bmad units."""
        return self.ref_scale * self.log_scale.exp()

    def transform(self, base: Tensor) -> Tensor:
        """Map base samples ``(n, dims)`` to particles ``(n, 6)`` [Bmad units]."""
        h = base
        layers = [m for m in self.mlp if isinstance(m, nn.Linear)]
        *hidden, last = layers
        for lin in hidden:
            h = _hidden_layer(h, lin.weight.T, lin.bias, self.dims)
        u = torch.addmm(last.bias, h, last.weight.T).addmm_(base, self.mix.T)
        if self.dims == 6:
            u = u.addmm_(quadratic_features(base), self.quad.T)
        # s0 * (b + exp(a) * u) with the (dims,) factors formed first: one
        # fused multiply-add over the particles
        x = torch.addcmul(
            self.ref_scale * self.offset, u, self.ref_scale * self.log_scale.exp()
        )
        if self.dims == 4:
            x = torch.cat([x, x.new_zeros(x.shape[0], 2)], dim=1)
        return x

    def forward(
        self,
        n: int,
        generator: torch.Generator | None = None,
        quasi_random: bool = False,
    ) -> Tensor:
        """Draw ``n`` fresh particles ``(n, 6)`` in Bmad coordinates.

        Args:
            n: Number of particles.
            generator: Random generator (on the device of the model).
            quasi_random: Use the Sobol sequence with a fresh random digital shift (see
                :func:`standard_normal_samples`) instead of i.i.d. samples.
        """
        p = self.log_scale
        base = standard_normal_samples(
            n, self.dims, generator, quasi_random, dtype=p.dtype, device=p.device
        )
        if n <= _SAMPLE_CHUNK or torch.is_grad_enabled():
            return self.transform(base)
        # sampling without gradients (evaluation, figures, particle files: ~10^6
        # particles in a default reconstruct): the MLP's (chunk, width)
        # intermediates stay cache-resident, ~1.3x faster; row by row the same
        # operations, so the same particles
        return torch.cat([self.transform(b) for b in base.split(_SAMPLE_CHUNK)])


#: Bits of the Sobol integers: ``u = (k + 1/2) / 2**23`` is exact in float32.
SOBOL_BITS = 23


def sobol_integers(
    n: int, dims: int, *, device: torch.device | str | None = None
) -> Tensor:
    """The first ``n`` points of the ``dims``-dimensional Sobol sequence as integers.

    Point ``i`` is ``k_i / 2**SOBOL_BITS`` with ``k_i`` in ``[0, 2**SOBOL_BITS)``
    (unscrambled; randomise with :func:`shifted_sobol_normals`).

    Shapes:
        ``(n, dims)`` int64.
    """
    engine = torch.quasirandom.SobolEngine(dims, scramble=False)
    u = engine.draw(n, dtype=torch.float64)  # multiples of 2**-30: exact
    return (u * 2**SOBOL_BITS).floor().to(dtype=torch.int64, device=device)


def shifted_sobol_normals(
    points: Tensor, generator: torch.Generator | None = None
) -> Tensor:
    """Standard normals from Sobol points with a fresh random digital shift.

    Each call XORs the integers ``points`` (from :func:`sobol_integers`) with one
    random ``SOBOL_BITS``-bit integer per dimension, maps them to the centres of
    their ``2**-SOBOL_BITS`` cells and through the inverse normal CDF. A digital
    shift keeps the net structure of the Sobol points (so the error of smooth
    averages stays ~1/n) while every point is uniform on [0, 1): the estimates
    are unbiased and fresh at every call. Everything happens on the device of
    ``points`` (a handful of kernels, no host synchronisation); the tails reach
    ``|z| = 5.3``.

    Args:
        points: Sobol integers on the target device.
        generator: Random generator on the device of ``points``.

    Shapes:
        ``(n, dims)`` int64 -> ``(n, dims)`` in the default float dtype.
    """
    shift = torch.randint(
        0,
        2**SOBOL_BITS,
        (points.shape[-1],),
        generator=generator,
        device=points.device,
    )
    u = torch.add(torch.bitwise_xor(points, shift), 0.5).mul_(2.0**-SOBOL_BITS)
    return torch.special.ndtri(u)


def standard_normal_samples(
    n: int,
    dims: int,
    generator: torch.Generator | None = None,
    quasi_random: bool = False,
    *,
    dtype: torch.dtype = torch.float32,
    device: torch.device | str | None = None,
) -> Tensor:
    """Standard-normal base samples, i.i.d. or randomised quasi-Monte Carlo.

    With ``quasi_random`` the points are the Sobol sequence with a new random
    digital shift drawn from ``generator`` at every call (see
    :func:`shifted_sobol_normals`), so samples are still fresh and unbiased,
    pushed through the inverse normal CDF. For a smooth generator
    the simulated images then carry far less shot noise than with i.i.d. points
    (error ~1/N instead of 1/sqrt(N)), which matters because the L1 image
    distance of a noisy image is biased towards narrower beams.

    Shapes:
        ``(n, dims)``.

    Example:
        >>> g = torch.Generator().manual_seed(0)
        >>> z = standard_normal_samples(4096, 4, g, quasi_random=True)
        >>> bool((z.mean(0).abs() < 1e-2).all())
        True
        >>> bool(((z.std(0) - 1).abs() < 1e-2).all())
        True
    """
    if not quasi_random:
        return torch.randn(n, dims, generator=generator, dtype=dtype, device=device)
    dev = generator.device if generator is not None else device
    points = sobol_integers(n, dims, device=dev)
    return shifted_sobol_normals(points, generator).to(dtype=dtype, device=device)


def quadratic_features(base: Tensor) -> Tensor:
    """Second-order products of standard-normal base samples, each of zero mean
    and unit variance: ``(u_i^2 - 1) / sqrt(2)`` and ``u_i u_j`` for ``i < j``
    (the second-order Hermite polynomials), ordered as ``torch.triu_indices``.

    Shapes:
        ``(n, d)`` -> ``(n, d (d + 1) / 2)``.

    Example:
        >>> quadratic_features(torch.tensor([[1.0, 2.0]]))
        tensor([[0.0000, 2.0000, 2.1213]])
    """
    i, j, diagonal = _product_indices(base.shape[-1], base.device)
    q = base[:, i] * base[:, j]
    return torch.where(diagonal, (q - 1) * math.sqrt(0.5), q)


#: ``(i, j, i == j)`` of :func:`quadratic_features` per dimension and device,
#: made once (every training step calls it)
_PRODUCT_INDICES: dict[tuple[int, torch.device], tuple[Tensor, Tensor, Tensor]] = {}


def _product_indices(d: int, device: torch.device) -> tuple[Tensor, Tensor, Tensor]:
    key = (d, device)
    out = _PRODUCT_INDICES.get(key)
    if out is None:
        i, j = torch.triu_indices(d, d, device=device)
        out = _PRODUCT_INDICES[key] = (i, j, i == j)
    return out


def tanh_layer(h: Tensor, weight_t: Tensor, bias: Tensor) -> Tensor:
    """``tanh(h @ weight_t + bias)``, computed as ``2 sigmoid(2 z) - 1``.

    torch's CPU ``tanh`` (SLEEF, AVX2) costs ~3x its ``sigmoid``: ~5.5 vs
    ~1.7 ns per element here, a quarter of a default 4D training step (issue
    12). The factor 2 rides on the matrix product (``alpha``, ``beta``), the
    ``2 s - 1`` is one kernel; the result is tanh to ~1e-7 absolute in
    float32 (a few rounding steps of ``s`` in [0, 1]). Training
    (:class:`_GeneratorFn`) and sampling (:meth:`BeamGenerator.transform`)
    both use it (4D, see :func:`_hidden_layer`), so that a trained generator
    samples what it was trained on.

    Shapes:
        ``h (n, i)``, ``weight_t (i, o)``, ``bias (o,)`` or ``(n, o)`` ->
        ``(n, o)``.
    """
    s = torch.addmm(bias, h, weight_t, beta=2, alpha=2).sigmoid_()
    minus_one = _MINUS_ONE.get((s.dtype, s.device))
    if minus_one is None:
        minus_one = torch.tensor(-1.0, dtype=s.dtype, device=s.device)
        _MINUS_ONE[(s.dtype, s.device)] = minus_one
    # out=s only where autograd does not need s (sigmoid's backward does)
    return torch.add(minus_one, s, alpha=2, out=None if s.requires_grad else s)


#: -1 per dtype and device: ``2 s - 1`` as ``torch.add(-1, s, alpha=2)``
_MINUS_ONE: dict[tuple[torch.dtype, torch.device], Tensor] = {}


def _hidden_layer(h: Tensor, weight_t: Tensor, bias: Tensor, dims: int) -> Tensor:
    """A hidden layer of the MLP: :func:`tanh_layer` for ``dims = 4``.

    6D keeps torch's ``tanh``: its defaults and acceptance runs (slow tests,
    ``benchmarks/reconstruction_6d*.py``) were validated with it, and a
    rounding-level change takes a different (equally good) training path that
    they would have to re-establish. 4D was checked with :func:`tanh_layer`
    on seeds 0-7 of the GPSR 4D benchmark (same accuracy).
    """
    if dims == 4:
        return tanh_layer(h, weight_t, bias)
    z = torch.addmm(bias, h, weight_t)
    return z.tanh_() if not z.requires_grad else z.tanh()


class FlatGenerator:
    """Training view of a :class:`BeamGenerator`: one flat parameter vector.

    The module's parameters become views of one tensor ``flat`` (so its
    ``state_dict``, snapshots and ``load_state_dict`` keep working), and
    :meth:`sample` runs the generator through a hand-written backward that
    writes the gradient of every parameter into one flat vector. An optimiser
    then updates all parameters with a few whole-vector kernels. Together this
    replaces the ~300 small autograd and optimiser operations of a step by ~40.

    Args:
        model: The generator (already on its training device and dtype).
        n: Particles per call of :meth:`sample`.
        quasi_random: Sobol base samples with a fresh digital shift per call
            (see :func:`shifted_sobol_normals`) instead of i.i.d. normals.
        shard: ``(index, count)``: this process draws share ``index`` of
            ``count`` equal shares of ``n`` particles (``n`` divisible by
            ``count``). With ``quasi_random`` and the same random generator
            state in every process the shares are consecutive blocks of the one
            Sobol sample that a single process would draw.

    Shapes:
        ``sample(generator)`` -> ``(n, dims)`` (only the generated coordinates;
        for ``dims = 4``, ``z = pz = 0``).
    """

    def __init__(
        self,
        model: BeamGenerator,
        n: int,
        quasi_random: bool,
        shard: tuple[int, int] = (0, 1),
    ) -> None:
        params = list(model.parameters())
        self.flat = torch.cat([p.detach().reshape(-1) for p in params])
        self.grad = torch.zeros_like(self.flat)
        self._grads: dict[str, Tensor] = {}
        start = 0
        for (name, p), _ in zip(model.named_parameters(), params, strict=True):
            stop = start + p.numel()
            p.data = self.flat[start:stop].view_as(p)
            self._grads[name] = self.grad[start:stop].view_as(p)
            start = stop
        self.flat.requires_grad_(True)
        self.model = model
        index, count = shard
        if n % count:
            raise ValueError(
                f"n_particles ({n}) must be divisible by the number of "
                f"processes ({count})."
            )
        self.n = n // count
        p = model.log_scale
        self.points = None
        if quasi_random:
            pts = sobol_integers(n, model.dims, device=p.device)
            self.points = pts[index * self.n : (index + 1) * self.n].contiguous()
            self._cells = torch.empty(
                self.n, model.dims, dtype=p.dtype, device=p.device
            )
            # half a cell: (k xor shift) 2**-SOBOL_BITS + this is the cell centre
            self._half_cell = torch.tensor(
                2.0 ** -(SOBOL_BITS + 1), dtype=p.dtype, device=p.device
            )
        # per-step views made once (each view is an ATen op; the step budget counts
        # them): the weights' transposes and the biases expanded to n rows
        linears = [lay for lay in model.mlp if isinstance(lay, nn.Linear)]
        self._linears = linears
        self._weights_t = [_transposed(lay.weight) for lay in linears]
        self._biases = [lay.bias.expand(self.n, lay.out_features) for lay in linears]
        self._mix_t = _transposed(model.mix)
        self._quad_t = _transposed(model.quad) if model.dims == 6 else None
        # 4D: the saved "quadratic features" placeholder, made once (a fresh
        # empty tensor per step was 5 of the step's ATen ops)
        self._no_quad = torch.empty(0, dtype=p.dtype, device=p.device)
        self._ones = torch.ones(self.n, dtype=p.dtype, device=p.device)
        self._names = [
            name[: -len(".weight")]
            for name, _ in model.named_parameters()
            if name.startswith("mlp.") and name.endswith(".weight")
        ]

    def base(self, generator: torch.Generator | None) -> Tensor:
        """Fresh standard-normal base samples ``(n, dims)`` on the device."""
        p = self.model.log_scale
        if self.points is None:
            return torch.randn(
                self.n,
                self.model.dims,
                generator=generator,
                dtype=p.dtype,
                device=p.device,
            )
        # shifted_sobol_normals(points, generator) in fewer kernels: the same
        # random shift, the same cell centres
        shift = torch.randint(
            0,
            2**SOBOL_BITS,
            (self.points.shape[-1],),
            generator=generator,
            device=self.points.device,
        )
        cells = self._cells.copy_(torch.bitwise_xor(self.points, shift))
        # (k xor shift + 1/2) 2**-SOBOL_BITS: the cell centres, exact in float32
        u = torch.add(self._half_cell, cells, alpha=2.0**-SOBOL_BITS, out=cells)
        return torch.special.ndtri(u)

    def sample(self, generator: torch.Generator | None) -> Tensor:
        """Fresh particles ``(n, dims)``, differentiable with respect to ``flat``."""
        return _GeneratorFn.apply(self.flat, self.base(generator), self)


def _transposed(t: Tensor) -> Tensor:
    """The transpose of a 2-D tensor as one strided view (a single ATen op)."""
    return t.as_strided(
        (t.shape[1], t.shape[0]), (t.stride(1), t.stride(0)), t.storage_offset()
    )


class _GeneratorFn(torch.autograd.Function):
    """``BeamGenerator.transform`` (without the zero columns) with its gradient."""

    @staticmethod
    def forward(ctx, flat: Tensor, base: Tensor, net: FlatGenerator) -> Tensor:  # type: ignore[override]
        m = net.model
        wts, biases = net._weights_t, net._biases
        hidden = [base]
        h = base
        for i in range(len(wts) - 1):
            h = _hidden_layer(h, wts[i], biases[i], m.dims)
            hidden.append(h)
        u = torch.addmm(biases[-1], h, wts[-1]).addmm_(base, net._mix_t)
        q = net._no_quad
        if m.dims == 6:
            q = quadratic_features(base)
            u = u.addmm_(q, net._quad_t)
        factor = m.ref_scale * m.log_scale.exp()
        x = torch.addcmul(m.ref_scale * m.offset, u, factor)
        ctx.save_for_backward(u, factor, q, *hidden)
        ctx.net = net
        return x

    @staticmethod
    def backward(ctx, gx: Tensor) -> tuple[Tensor, None, None]:  # type: ignore[override]
        u, factor, q, *hidden = ctx.saved_tensors
        net = ctx.net
        m = net.model
        g = net._grads
        gu = gx * factor
        torch.sum(gu * u, 0, out=g["log_scale"])
        gx_sum = gx.sum(0)
        torch.mul(gx_sum, m.ref_scale, out=g["offset"])
        gu_t = _transposed(gu)
        torch.mm(gu_t, hidden[0], out=g["mix"])
        if m.dims == 6:
            torch.mm(gu_t, q, out=g["quad"])
        names = net._names
        linears = net._linears
        ga, ga_t = gu, gu_t
        for i in range(len(linears) - 1, -1, -1):
            torch.mm(ga_t, hidden[i], out=g[names[i] + ".weight"])
            if i == len(linears) - 1:  # sum of gu = factor * sum of gx
                torch.mul(gx_sum, factor, out=g[names[i] + ".bias"])
            else:  # a column sum as a matrix-vector product: 2 ATen ops, not 3
                torch.mv(ga_t, net._ones, out=g[names[i] + ".bias"])
            if i > 0:
                gh = torch.mm(ga, linears[i].weight)
                ga = torch.ops.aten.tanh_backward(gh, hidden[i])
                ga_t = _transposed(ga)
        return net.grad, None, None
