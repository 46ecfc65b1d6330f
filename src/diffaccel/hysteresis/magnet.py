"""Hysteretic magnets: a Preisach model of the current history drives an element.

A :class:`HystereticMagnet` composes a :class:`~diffaccel.hysteresis.PreisachModel`
(current [A] -> integrated gradient [T]) with the calibration
``k1 = G / (L * B rho)``, ``B rho = p0c / (c |q|)``, and names the quadrupole
parameter it sets. :func:`hysteretic_settings` turns the current histories of
several magnets into the ``settings``/``names`` pair that
:meth:`diffaccel.dynamics.Beamline.track` takes, so tracking, reconstruction and
optimisation see the magnets' real (history-dependent) focusing.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor, nn

from diffaccel.dynamics import ELECTRON, SPEED_OF_LIGHT, Species
from diffaccel.hysteresis.preisach import PreisachModel

__all__ = ["HystereticMagnet", "hysteretic_settings", "magnetic_rigidity"]


def magnetic_rigidity(p0c: Tensor | float, species: Species = ELECTRON) -> Tensor:
    """Magnetic rigidity ``B rho = p0c / (c |q|)`` of the reference particle.

    Args:
        p0c: Reference momentum times c [eV], scalar or any shape.
        species: Particle species (its charge in units of e).

    Returns:
        ``B rho`` [T m], same shape as ``p0c`` (float64 if ``p0c`` is a number).

    Raises:
        ValueError: if any ``p0c`` is not positive and finite.

    Example:
        >>> round(float(magnetic_rigidity(43.36e6)), 4)  # 43.36 MeV/c electrons
        0.1446
    """
    p = torch.as_tensor(p0c, dtype=torch.float64 if not torch.is_tensor(p0c) else None)
    if not torch.isfinite(p).all() or (p <= 0).any():
        raise ValueError(f"p0c must be positive and finite [eV]; got {p.tolist()}.")
    return p / (SPEED_OF_LIGHT * abs(species.charge))


class HystereticMagnet(nn.Module):
    """Quadrupole excitation that follows a Preisach model of its current history.

    The Preisach model maps the current history [A] to the integrated gradient
    ``G`` [T] (e.g. fitted with :func:`~diffaccel.hysteresis.fit_preisach` on
    rotating-coil data); this class adds the beam calibration
    ``k1 = G / (length * B rho)`` [1/m^2] and the name of the element parameter it
    drives. It holds no state: histories and states are passed explicitly.

    Args:
        element: Name of the quadrupole in the beamline (``"Q1"`` sets ``"Q1.k1"``).
        preisach: Model of the integrated gradient [T] versus current [A].
        length: Magnetic length [m] of the quadrupole, > 0.

    Shapes:
        Currents ``(*B, T)`` give integrated gradients and ``k1`` of ``(*B, T)``;
        states are ``(*B, M)``.

    Raises:
        ValueError: if ``length`` is not positive or ``element`` is empty.

    Example:
        >>> from diffaccel.hysteresis import PreisachMesh, PreisachModel
        >>> pm = PreisachModel(PreisachMesh.triangular(n=10), input_range=(0.0, 10.0))
        >>> q1 = HystereticMagnet("Q1", pm, length=0.1)
        >>> q1.k1(torch.tensor([0.0, 10.0, 5.0]), p0c=43.36e6).shape
        torch.Size([3])
    """

    def __init__(self, element: str, preisach: PreisachModel, length: float) -> None:
        super().__init__()
        if not element:
            raise ValueError("HystereticMagnet needs the name of its element.")
        if not float(length) > 0:
            raise ValueError(f"magnet length must be > 0 m; got {length} m.")
        self.element = element
        self.preisach = preisach
        self.length = float(length)

    @property
    def setting_name(self) -> str:
        """Beamline setting driven by this magnet, e.g. ``"Q1.k1"``."""
        return f"{self.element}.k1"

    def integrated_gradient(
        self, current: Tensor, initial_state: str | Tensor | None = None
    ) -> Tensor:
        """Integrated gradient [T] after each step of the current history.

        Args:
            current: Currents [A] in the order applied, shape ``(*B, T)``.
            initial_state: State before the history (see
                :meth:`PreisachModel.initial_states`).

        Returns:
            Integrated gradient [T], shape ``(*B, T)``.
        """
        return self.preisach(current, initial_state=initial_state)

    def k1(
        self,
        current: Tensor,
        p0c: Tensor | float,
        initial_state: str | Tensor | None = None,
        species: Species = ELECTRON,
    ) -> Tensor:
        """Normalised gradient ``k1`` [1/m^2] after each step of the history.

        Args:
            current: Currents [A] in the order applied, shape ``(*B, T)``.
            p0c: Reference momentum times c [eV].
            initial_state: State before the history.
            species: Tracked species (rigidity uses ``|charge|``).

        Returns:
            ``k1`` [1/m^2], shape ``(*B, T)``.
        """
        g = self.integrated_gradient(current, initial_state)
        brho = magnetic_rigidity(p0c, species).to(g)
        return g / (self.length * brho)

    def final_state(
        self, current: Tensor, initial_state: str | Tensor | None = None
    ) -> Tensor:
        """Hysteron states after the current history, shape ``(*B, M)``."""
        return self.preisach.final_state(current, initial_state=initial_state)


def hysteretic_settings(
    magnets: Sequence[HystereticMagnet],
    currents: Tensor,
    p0c: Tensor | float,
    initial_states: Sequence[str | Tensor | None] | None = None,
    species: Species = ELECTRON,
) -> tuple[Tensor, list[str]]:
    """Beamline settings for current histories of several hysteretic magnets.

    Args:
        magnets: ``P`` magnets, one per column of ``currents``.
        currents: Currents [A] applied in order, shape ``(*B, T, P)``.
        p0c: Reference momentum times c [eV].
        initial_states: Per magnet, its state before the history (``None``: the
            model's own).
        species: Tracked species.

    Returns:
        ``(settings, names)``: ``k1`` [1/m^2] of shape ``(*B, T, P)`` and the
        ``P`` setting names, ready for ``Beamline.track(particles, p0c, settings,
        names)`` (``T`` acts as the scan dimension ``K``).

    Raises:
        ValueError: if ``magnets`` is empty, the last dimension of ``currents``
            is not ``P`` or the magnets drive the same element twice.
    """
    p = len(magnets)
    if p < 1:
        raise ValueError("magnets is empty; give at least one HystereticMagnet.")
    if currents.dim() < 2 or currents.shape[-1] != p:
        raise ValueError(
            f"currents must have shape (*B, T, P) with P = {p} magnets; got "
            f"{tuple(currents.shape)}."
        )
    names = [m.setting_name for m in magnets]
    if len(set(names)) != p:
        raise ValueError(f"each magnet must drive its own element; got {names}.")
    states = list(initial_states) if initial_states is not None else [None] * p
    if len(states) != p:
        raise ValueError(f"need {p} initial states; got {len(states)}.")
    cols = [
        m.k1(currents[..., j], p0c, initial_state=s, species=species)
        for j, (m, s) in enumerate(zip(magnets, states, strict=True))
    ]
    return torch.stack(cols, dim=-1), names
