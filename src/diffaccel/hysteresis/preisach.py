"""Differentiable Preisach model: input history -> hysteretic output."""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn

from diffaccel.dynamics import as_real_tensor
from diffaccel.hysteresis.mesh import PreisachMesh, Warp, check_warp, warp_input
from diffaccel.hysteresis.states import (
    RowLayout,
    demagnetized_state,
    exact_magnetization,
    exact_states,
    smooth_states,
)
from diffaccel.hysteresis.stream import (
    RANGE_TOL,
    InputRangeWarning,
    StreamSpec,
    warn_outside_range,
)

__all__ = ["INITIAL_STATES", "InputRangeWarning", "PreisachModel"]

INITIAL_STATES = ("negative", "positive", "demagnetized", "learned")
# start of the virtual history of each initial state (normalised input)
_START = {"negative": 0.0, "positive": 1.0, "demagnetized": 0.5, "learned": 0.5}


def _positive(raw: Tensor) -> Tensor:
    """The one map from raw (unconstrained) to non-negative parameters."""
    return F.softplus(raw)


def _inverse_positive(value: Tensor) -> Tensor:
    """Inverse of :func:`_positive` for ``value > 0``."""
    return value + torch.log(-torch.expm1(-value))


class PreisachModel(nn.Module):
    """Preisach hysteresis model of a magnet: current history -> field.

    The output is ``offset + slope * u_n + scale * m(u_n)`` in normalised output
    units, mapped back to physical units by ``output_loc + output_scale * (.)``.
    Here ``u_n = (u - lo) / (hi - lo)`` is the normalised input and
    ``m = sum_i w_i s_i / sum_i w_i`` the normalised Preisach integral, with
    hysteron weights ``w = area * density`` and states ``s`` in ``[-1, 1]``.
    ``density`` is non-negative: ``softplus(raw_density)``; a ``symmetric``
    model averages it with its mirror image, ``mu(alpha, beta) =
    mu(1 - beta, 1 - alpha)`` (symmetric about the centre of the input range, as
    for magnets and soft magnetic materials: the ascending major branch then
    determines the descending one; with ``odd`` the offset follows from the
    slope so that the output is odd about zero input). The mesh may be regular
    in a warped input (``mesh_warp``), which places the thresholds where the
    material switches. Inputs beyond the input range leave every
    hysteron switched (saturation) while the linear term ``slope * u_n``
    continues; they raise an :class:`InputRangeWarning`. The normalisation
    buffers ``output_loc`` and ``output_scale`` are set by
    :func:`~diffaccel.hysteresis.fit_preisach` from the training data (default
    ``0`` and ``1``).

    Parameters and buffers are float64 unless ``dtype`` says otherwise; inputs
    are cast to the model's dtype and device. ``model.to(torch.float32)`` works
    as for any module.

    Args:
        mesh: Hysteron mesh on the normalised plane; default
            ``PreisachMesh.triangular(n=30)`` (465 hysterons).
        input_range: ``(lo, hi)`` input range [input units, e.g. A] of the
            hysterons; inputs beyond it saturate (with a warning).
        initial_state: State before the first input: ``"negative"``
            (saturated down, default: the magnet was last cycled down to the
            bottom of the range), ``"positive"``, ``"demagnetized"`` or
            ``"learned"`` (a trainable state per hysteron, ``tanh(raw)``).
        smoothing: Width of the smooth relays [input units], used only by the
            ``smooth=True`` calls; default 1 % of the input range.
        symmetric: Tie the density to its mirror image about the centre of
            the input range; needs a mirror-symmetric mesh (triangular ones are).
        dtype: Floating dtype of parameters and buffers.
        mesh_warp: Knots ``(u, t)`` [1, normalised input units] when ``mesh``
            is regular in the warped coordinate of
            :func:`~diffaccel.hysteresis.mesh.warp_input` (as built by
            ``PreisachMesh.triangular(..., warp=...)``); ``None`` for a mesh
            regular in the input. The relays use the thresholds as they
            are; the warp names the coordinates of the plane in which the
            mesh is regular, used by the predictive band's prior
            (:meth:`plane_coordinates`). Saved with :meth:`config`.
        odd: Make the output odd in the input, ``y(-u, mirrored state) =
            -y(u, state)``, as ``B(H)`` of a soft magnetic material: the
            offset follows from the slope and the output normalisation,
            ``offset = -output_loc / output_scale - slope / 2``, rather than
            being fitted (the ``offset`` parameter holds that value after a
            fit). Needs ``symmetric`` and an input range centred on zero.

    Shapes:
        Inputs ``u`` are ``(*B, T)`` (time last); ``states`` returns
        ``(*B, T, M)``, ``magnetization`` and ``forward`` ``(*B, T)``,
        ``final_state`` ``(*B, M)``.

    Raises:
        ValueError: for an empty or inverted input range, an unknown initial
            state, a non-positive smoothing width or ``symmetric`` with a mesh
            that is not mirror symmetric.

    Example:
        >>> mesh = PreisachMesh.triangular(n=10)
        >>> model = PreisachModel(mesh, input_range=(0.0, 10.0))
        >>> u = torch.tensor([0.0, 10.0, 5.0, 0.0, 5.0])
        >>> y = model(u)  # untrained: offset 0, slope 1, scale 1 in normalised units
        >>> bool(y[2] > y[4])  # same input, higher output on the falling branch
        True
    """

    def __init__(
        self,
        mesh: PreisachMesh | None = None,
        input_range: Sequence[float] = (0.0, 1.0),
        initial_state: str = "negative",
        smoothing: float | None = None,
        symmetric: bool = False,
        dtype: torch.dtype = torch.float64,
        mesh_warp: Warp | None = None,
        odd: bool = False,
    ) -> None:
        super().__init__()
        if not (isinstance(dtype, torch.dtype) and dtype.is_floating_point):
            raise ValueError(
                f"dtype must be a floating torch dtype (e.g. torch.float64); "
                f"got {dtype}."
            )
        lo, hi = (float(v) for v in input_range)
        if not (math.isfinite(lo) and math.isfinite(hi)) or hi <= lo:
            raise ValueError(
                f"input_range must be finite with lo < hi; got ({lo}, {hi})."
            )
        if initial_state not in INITIAL_STATES:
            raise ValueError(
                f"initial_state must be one of {INITIAL_STATES}; got {initial_state!r}."
            )
        if smoothing is None:
            smoothing = 0.01 * (hi - lo)
        if not (smoothing > 0 and math.isfinite(smoothing)):
            raise ValueError(f"smoothing must be a positive width; got {smoothing}.")
        mesh = mesh if mesh is not None else PreisachMesh.triangular(n=30, dtype=dtype)
        mesh = mesh.to(dtype=dtype)
        self.input_range = (lo, hi)
        self.odd = bool(odd)
        if self.odd and not (symmetric and abs(lo + hi) <= 1e-9 * (hi - lo)):
            raise ValueError(
                "odd=True needs symmetric=True and an input range centred on 0; "
                f"got symmetric={symmetric}, range ({lo}, {hi})."
            )
        self.mesh_warp = check_warp(mesh_warp)
        self.initial_state_kind = initial_state
        self.smoothing = float(smoothing)
        self.register_buffer("alpha", mesh.alpha.clone())
        self.register_buffer("beta", mesh.beta.clone())
        self.register_buffer("area", mesh.area.clone())
        self.symmetric = bool(symmetric)
        mirror = mesh.mirror_index() if self.symmetric else torch.arange(len(mesh))
        self.register_buffer("mirror", mirror.to(mesh.alpha.device), persistent=False)
        self._layout = RowLayout(self.alpha, self.beta)
        m = len(mesh)
        one = torch.ones((), dtype=dtype)
        self.raw_density = nn.Parameter(_inverse_positive(one).expand(m).clone())
        self.offset = nn.Parameter(torch.zeros((), dtype=dtype))
        self.slope = nn.Parameter(torch.ones((), dtype=dtype))
        self.scale = nn.Parameter(torch.ones((), dtype=dtype))
        self.register_buffer("output_loc", torch.zeros((), dtype=dtype))
        self.register_buffer("output_scale", torch.ones((), dtype=dtype))
        if initial_state == "learned":
            self.raw_initial_state = nn.Parameter(torch.zeros(m, dtype=dtype))
        else:
            self.raw_initial_state = None

    # ------------------------------------------------------------ serialising
    def config(self) -> dict:
        """JSON-serialisable settings; with ``state_dict()`` they rebuild the model."""
        return {
            "type": "PreisachModel",
            "input_range": list(self.input_range),
            "initial_state": self.initial_state_kind,
            "smoothing": self.smoothing,
            "symmetric": self.symmetric,
            "odd": self.odd,
            "mesh_warp": (
                None if self.mesh_warp is None else [list(k) for k in self.mesh_warp]
            ),
            "dtype": str(self.alpha.dtype).removeprefix("torch."),
            "n_hysterons": int(self.alpha.numel()),
        }

    @classmethod
    def from_config(cls, config: dict, state_dict: dict[str, Tensor]) -> PreisachModel:
        """Rebuild a model from :meth:`config` and ``state_dict()``.

        Args:
            config: Output of :meth:`config` (e.g. read back from JSON).
            state_dict: Tensors of ``state_dict()`` (e.g. from
                ``torch.load(..., weights_only=True)``); the mesh comes from its
                ``alpha``, ``beta`` and ``area``.

        Raises:
            ValueError: if the config is not a Preisach model's or tensors miss.
        """
        if config.get("type") != "PreisachModel":
            raise ValueError(
                f"not a PreisachModel config: type {config.get('type')!r}."
            )
        missing = {"alpha", "beta", "area", "raw_density"} - set(state_dict)
        if missing:
            raise ValueError(f"state_dict misses {sorted(missing)}.")
        name = str(config.get("dtype", "float64"))
        dtype = getattr(torch, name, None)
        if not isinstance(dtype, torch.dtype) or not dtype.is_floating_point:
            raise ValueError(
                f"config dtype must name a floating torch dtype such as 'float64'; "
                f"got {name!r}."
            )
        mesh = PreisachMesh(state_dict["alpha"], state_dict["beta"], state_dict["area"])
        model = cls(
            mesh,
            input_range=config["input_range"],
            initial_state=config["initial_state"],
            smoothing=config["smoothing"],
            symmetric=bool(config.get("symmetric", False)),
            dtype=dtype,
            mesh_warp=config.get("mesh_warp"),
            odd=bool(config.get("odd", False)),
        )
        model.load_state_dict(state_dict)
        return model

    # ------------------------------------------------------------------ helpers
    def _apply(self, fn, recurse=True):  # keep the row layout with the buffers
        out = super()._apply(fn, recurse)
        self._layout.to(self.alpha.device, self.alpha.dtype)
        return out

    @property
    def mesh(self) -> PreisachMesh:
        """The hysteron mesh (a copy of the buffers)."""
        return PreisachMesh(self.alpha, self.beta, self.area)

    def effective_offset(self) -> Tensor:
        """The offset the output uses [normalised output]: fitted, or from
        ``odd`` (``-output_loc / output_scale - slope / 2``)."""
        if self.odd:
            return -self.output_loc / self.output_scale - 0.5 * self.slope
        return self.offset

    def plane_coordinates(self) -> tuple[Tensor, Tensor]:
        """Hysteron thresholds in the coordinates the mesh is regular in [1].

        ``warp_input(alpha), warp_input(beta)`` with the model's
        ``mesh_warp`` (the normalised thresholds themselves without one),
        shapes ``(M,)``.
        """
        return warp_input(self.alpha, self.mesh_warp), warp_input(
            self.beta, self.mesh_warp
        )

    @property
    def density(self) -> Tensor:
        """Non-negative hysteron density [1], shape ``(M,)`` (mirror symmetric
        when ``symmetric``)."""
        d = _positive(self.raw_density)
        return 0.5 * (d + d[self.mirror]) if self.symmetric else d

    @density.setter
    def density(self, value: Tensor) -> None:
        value = as_real_tensor(
            value, "density", dtype=self.alpha.dtype, device=self.alpha.device
        )
        if value.shape != self.raw_density.shape or not (value > 0).all():
            raise ValueError(
                f"density must be positive with shape {tuple(self.raw_density.shape)}."
            )
        with torch.no_grad():
            self.raw_density.copy_(_inverse_positive(value))

    @property
    def weights(self) -> Tensor:
        """Hysteron weights ``area * density``, shape ``(M,)``."""
        return self.area * self.density

    def normalize_input(self, u: Tensor) -> Tensor:
        """Map inputs [input units] to normalised inputs [1] and check them.

        Inputs beyond ``input_range`` are kept (they map below 0 or above 1) and
        raise an :class:`InputRangeWarning` naming how far outside they lie;
        the hysterons see them clipped to the range (saturation).

        Raises:
            ValueError: if ``u`` has no time axis or NaN/inf values.
        """
        u = as_real_tensor(
            u, "inputs", dtype=self.alpha.dtype, device=self.alpha.device
        )
        if u.ndim < 1 or u.shape[-1] < 1:
            raise ValueError(
                f"inputs need shape (*B, T) with T >= 1; got {tuple(u.shape)}."
            )
        if not torch.isfinite(u).all():
            raise ValueError("inputs contain NaN or infinite values.")
        lo, hi = self.input_range
        un = (u - lo) / (hi - lo)
        below, above = float(-un.min()), float(un.max() - 1.0)
        if below > RANGE_TOL or above > RANGE_TOL:
            warn_outside_range(
                float(u.min()), float(u.max()), below, above, (lo, hi), stacklevel=2
            )
        return un

    def check_input_range(self, u: Tensor, what: str = "inputs") -> None:
        """Raise if finite inputs lie outside ``input_range`` (for training data).

        Args:
            u: Inputs [input units], any shape.
            what: Name of the inputs in the message.

        Raises:
            ValueError: naming the span of ``u`` and the ``input_range``.
        """
        u = as_real_tensor(u, what, dtype=self.alpha.dtype, device=self.alpha.device)
        lo, hi = self.input_range
        tol = RANGE_TOL * (hi - lo)
        if u.numel() and (float(u.min()) < lo - tol or float(u.max()) > hi + tol):
            raise ValueError(
                f"{what} span {float(u.min()):.6g} .. {float(u.max()):.6g}, outside "
                f"the model's input_range [{lo:.6g}, {hi:.6g}]; build the model "
                "with an input_range that holds them."
            )

    def initial_states(self, initial_state: str | Tensor | None = None) -> Tensor:
        """Hysteron states before the first input, shape ``(M,)`` or ``(*B, M)``.

        Args:
            initial_state: ``None`` (the model's own), one of
                ``"negative" | "positive" | "demagnetized" | "learned"``, or a
                tensor of states in ``[-1, 1]`` (e.g. from :meth:`final_state`).
        """
        kind = self.initial_state_kind if initial_state is None else initial_state
        m = self.alpha.numel()
        if isinstance(kind, Tensor):
            s = as_real_tensor(
                kind, "initial_state", dtype=self.alpha.dtype, device=self.alpha.device
            )
            if s.shape[-1:] != (m,):
                raise ValueError(
                    f"initial_state tensor must have shape (*B, {m}); got "
                    f"{tuple(s.shape)}."
                )
            if not torch.isfinite(s).all() or (s.abs() > 1 + 1e-12).any():
                raise ValueError("initial_state tensor must be finite and in [-1, 1].")
            return s
        if kind == "negative":
            return -torch.ones_like(self.alpha)
        if kind == "positive":
            return torch.ones_like(self.alpha)
        if kind == "demagnetized":
            return demagnetized_state(self.alpha, self.beta)
        if kind == "learned":
            if self.raw_initial_state is None:
                raise ValueError(
                    "initial_state='learned' needs a model built with "
                    "initial_state='learned'."
                )
            return torch.tanh(self.raw_initial_state)
        raise ValueError(
            f"initial_state must be one of {INITIAL_STATES} or a tensor; got {kind!r}."
        )

    def _start(self, initial_state: str | Tensor | None) -> float:
        kind = self.initial_state_kind if initial_state is None else initial_state
        return 0.5 if isinstance(kind, Tensor) else _START[kind]

    # ------------------------------------------------------------------ physics
    def states(
        self,
        u: Tensor,
        initial_state: str | Tensor | None = None,
        smooth: bool = False,
    ) -> Tensor:
        """Hysteron states along input sequences.

        Args:
            u: Inputs [input units], shape ``(*B, T)``.
            initial_state: See :meth:`initial_states`.
            smooth: Exact relays (``False``) or smooth, rate-independent relays
                of width ``smoothing`` (``True``), differentiable in ``u``. The
                smooth sequence starts from a virtual turning point at the
                bottom of the range (``"negative"``), the top (``"positive"``)
                or the centre (``"demagnetized"``, ``"learned"`` and tensor
                states); to continue smoothly after a history, use
                :meth:`predict` with ``history`` rather than a tensor state.

        Returns:
            States in ``[-1, 1]``, shape ``(*B, T, M)``.
        """
        return self._normalized_states(self.normalize_input(u), initial_state, smooth)

    def _normalized_states(
        self, un: Tensor, initial_state: str | Tensor | None, smooth: bool = False
    ) -> Tensor:
        """:meth:`states` of already checked, normalised inputs ``(*B, T)``."""
        un = un.clamp(0.0, 1.0)  # saturation beyond the range
        s0 = self.initial_states(initial_state)
        if smooth:
            width = self.smoothing / (self.input_range[1] - self.input_range[0])
            return smooth_states(
                un, self.alpha, self.beta, s0, width, self._start(initial_state)
            )
        return exact_states(un, self.alpha, self.beta, s0, self._layout)

    def magnetization(
        self,
        u: Tensor,
        initial_state: str | Tensor | None = None,
        smooth: bool = False,
    ) -> Tensor:
        """Normalised Preisach integral ``sum(w * s) / sum(w)`` along sequences.

        Exact mode never builds the ``(T, M)`` state table (see
        :func:`~diffaccel.hysteresis.states.exact_magnetization`); gradients
        flow to the density and a learned initial state.

        Args:
            u: Inputs [input units], shape ``(*B, T)``.
            initial_state: See :meth:`initial_states`.
            smooth: See :meth:`states`.

        Returns:
            Magnetization in ``[-1, 1]``, shape ``(*B, T)``.
        """
        return self._magnetization(self.normalize_input(u), initial_state, smooth)

    def _magnetization(
        self, un: Tensor, initial_state: str | Tensor | None, smooth: bool
    ) -> Tensor:
        """:meth:`magnetization` of already checked, normalised inputs."""
        w = self.weights
        if smooth:
            return (self._normalized_states(un, initial_state, True) @ w) / w.sum()
        s0 = self.initial_states(initial_state)
        un = un.clamp(0.0, 1.0)  # saturation beyond the range
        return exact_magnetization(un, self._layout, w, s0) / w.sum()

    def forward(
        self,
        u: Tensor,
        initial_state: str | Tensor | None = None,
        smooth: bool = False,
    ) -> Tensor:
        """Output along input sequences [output units].

        Args:
            u: Inputs [input units], shape ``(*B, T)``.
            initial_state: See :meth:`initial_states`.
            smooth: See :meth:`states`.

        Returns:
            Outputs [output units], shape ``(*B, T)``.
        """
        un = self.normalize_input(u)
        return self._output(un, self._magnetization(un, initial_state, smooth))

    def _output(self, un: Tensor, m: Tensor) -> Tensor:
        """Output [output units] from normalised inputs and magnetization."""
        y = self.effective_offset() + self.slope * un + self.scale * m
        return self.output_loc + self.output_scale * y

    def final_state(
        self, u: Tensor, initial_state: str | Tensor | None = None
    ) -> Tensor:
        """Exact hysteron states after the history ``u``.

        Pass the result as ``initial_state`` to continue from it in exact mode:
        ``model(v, initial_state=model.final_state(u))`` equals the tail of
        ``model(cat(u, v))``.

        Args:
            u: History of inputs [input units], shape ``(*B, T)``.
            initial_state: State before the history, see :meth:`initial_states`.

        Returns:
            States in ``[-1, 1]``, shape ``(*B, M)``.
        """
        un = self.normalize_input(u).clamp(0.0, 1.0)
        s0 = self.initial_states(initial_state)
        return exact_states(un, self.alpha, self.beta, s0, self._layout, last=True)

    def stream_spec(self, initial_state: str | Tensor | None = None) -> StreamSpec:
        """The model's numbers for streaming long histories (numpy, no gradients).

        Args:
            initial_state: State before the history (one history: shape
                ``(M,)``), see :meth:`initial_states`.

        Returns:
            A :class:`~diffaccel.hysteresis.stream.StreamSpec` without a band
            (``LaplaceBand.stream_spec`` adds one), float64.
        """
        with torch.no_grad():
            s0 = self.initial_states(initial_state)
            if s0.ndim != 1:
                raise ValueError(
                    f"streaming needs one history: initial state shape "
                    f"({self.alpha.numel()},); got {tuple(s0.shape)}."
                )
            w = self.weights
            return StreamSpec(
                input_range=self.input_range,
                alpha=_host(self.alpha),
                beta=_host(self.beta),
                weights=_host(w / w.sum()),
                initial=_host(s0),
                offset=float(self.effective_offset()),
                slope=float(self.slope),
                scale=float(self.scale),
                output_loc=float(self.output_loc),
                output_scale=float(self.output_scale),
            )

    def predict(
        self,
        u: Tensor,
        history: Tensor | None = None,
        initial_state: str | Tensor | None = None,
        smooth: bool = False,
    ) -> Tensor:
        """Output for a future input sequence, continuing after ``history``.

        Args:
            u: Future inputs [input units], shape ``(*B, T)``.
            history: Past inputs [input units], shape ``(*B, H)`` or ``(H,)``;
                ``None`` starts from ``initial_state``.
            initial_state: State before the history, see :meth:`initial_states`.
            smooth: See :meth:`states`.

        Returns:
            Outputs [output units] for the future steps, shape ``(*B, T)``.

        Raises:
            ValueError: if the batch shapes of ``history`` and ``u`` do not
                broadcast (also a ``RuntimeError``, as raised before).
        """
        u = as_real_tensor(u, "u", dtype=self.alpha.dtype, device=self.alpha.device)
        if history is None:
            return self(u, initial_state, smooth=smooth)
        h = as_real_tensor(
            history, "history", dtype=self.alpha.dtype, device=self.alpha.device
        )
        if h.ndim < 1 or h.shape[-1] < 1 or u.ndim < 1:
            raise ValueError(
                f"history and u need shape (*B, T); got {tuple(h.shape)}, "
                f"{tuple(u.shape)}."
            )
        try:
            batch = torch.broadcast_shapes(h.shape[:-1], u.shape[:-1])
        except RuntimeError:
            raise _BatchShapeError(
                f"history and u need broadcastable batch shapes *B: history "
                f"{tuple(h.shape)} (*B, H) and u {tuple(u.shape)} (*B, T) do not "
                "match."
            ) from None
        h = h.expand(*batch, h.shape[-1])
        u = u.expand(*batch, u.shape[-1])
        full = torch.cat([h, u], dim=-1)
        return self(full, initial_state, smooth=smooth)[..., h.shape[-1] :]


class _BatchShapeError(ValueError, RuntimeError):
    """Mismatched batch shapes: a ValueError that is also a RuntimeError."""


def _host(x: Tensor) -> np.ndarray:
    """A float64 numpy copy of ``x`` (detached, on the host)."""
    return x.detach().to(device="cpu", dtype=torch.float64).numpy().copy()
