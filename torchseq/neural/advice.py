"""What ``fit`` and the command line say about a model's settings: one short line each.

Each function returns its message, or None where there is nothing to say; the caller warns
(``NeuralSeqSLAM.fit`` with :func:`warnings.warn`, the command line in its own notes), and
names the setting as its user spells it (``n_output`` or ``--neural-n-output``). The
figures behind each message are on the results page it links.
"""

from __future__ import annotations

from torchseq.neural.selfcheck import SELF_CHECK_FLOOR

COARSE_UNIT_FRAMES = 8  # frames per unit past which even the interpolating readout fails
LONG_ROUTES = "docs/results/neural-long-routes.md"
NEURAL = "docs/results/neural.md"


def coarse_units(n_frames: int, n_units: int, readout: str, search: bool = False,
                 n_output: str = "n_output") -> str | None:
    """What units of several frames cost the stage that decides, or None where nothing.

    Measured on demo routes (docs/results/neural.md, "Long routes"): 5.4 frames per unit
    cost the centre readout a fifth of its recall@1 (the interpolating readout keeps it); 36
    frames per unit fail both. On nordland-b (``experiments/neural_long_route.py``) 3.2
    frames per unit take the ring's recall@1 from 0.59 to 0.25; the unit search (``search``)
    gets 0.75.

    Args:
        n_frames: reference frames.
        n_units: output units.
        readout: the ring's ``readout``.
        search: the unit search decides (its figures, not the ring's).
        n_output: how the caller spells the setting.
    """
    per_unit = n_frames / n_units
    head = (f"a route of {n_frames} frames on {n_units} output units ({n_output}): "
            f"{per_unit:.1f} frames per unit")
    if search and per_unit > 1:
        if per_unit <= COARSE_UNIT_FRAMES:
            return f"{head}, so the ring alone blurs the route; the unit search decides " \
                   f"({LONG_ROUTES})"
        return (f"{head}: past {COARSE_UNIT_FRAMES} the unit search degrades too; raise "
                f"{n_output} ({LONG_ROUTES})")
    if per_unit <= 1 or (readout == "interpolate" and per_unit <= COARSE_UNIT_FRAMES):
        return None
    if per_unit > COARSE_UNIT_FRAMES:
        return (f"{head}: past {COARSE_UNIT_FRAMES} any readout fails; raise {n_output} "
                f"({LONG_ROUTES})")
    return (f"{head}, so readout {readout!r} places are no finer; readout='interpolate' reads "
            f"within a unit ({LONG_ROUTES})")


def self_check(figure: float, n_frames: int, n_units: int, search: bool = False,
               n_output: str = "n_output") -> str | None:
    """Say when the model separates its own reference poorly (see ``selfcheck.py``).

    With the unit search deciding (``search``) the figure no longer predicts a collapse on
    nordland-b (self-check 0.86 there, recall@1 0.75): the advice says so.
    """
    if figure >= SELF_CHECK_FLOOR:
        return None
    head = (f"self-check: only {figure:.2f} of the reference frames, disturbed, win "
            f"their own unit (floor {SELF_CHECK_FLOOR})")
    advice = (f"the unit search reads sequences; raise {n_output} for single-frame places"
              if search else f"expect a collapse on a real query; raise {n_output}")
    return f"{head}: {advice} ({LONG_ROUTES})"


def adaptive_units(n_frames: int, n_units: int, ring_velocity: str,
                   n_output: str = "n_output") -> str | None:
    """Say when the adaptive ring gets units of two or more frames.

    Measured (docs/results/neural.md, "Long routes"): it helps while each unit holds one
    frame and costs recall past about two (3,000 frames on 555 units, interpolate: 0.994 ->
    0.953; corridor at 55 units: 0.798 -> 0.741), where the fixed ring is the better choice.
    """
    per_unit = n_frames / n_units
    if ring_velocity != "adaptive" or per_unit < 2:
        return None
    return (f"ring_velocity='adaptive' on {per_unit:.1f} frames per unit: worse than the fixed "
            f"ring; raise {n_output} to {n_frames} or use 'fixed' ({NEURAL}, Long routes)")


def novelty_without_effect(n_frames: int, n_output_value: int, recruit: str,
                           n_output: str = "n_output") -> str | None:
    """Say when ``recruit="novelty"`` cannot change the model (one frame per unit).

    With ``R <= n_output`` both rules give every frame its own unit, so the model is the
    uniform one bit for bit; without a word a user would read equal recall as the rule's
    measured effect.
    """
    if recruit != "novelty" or n_frames > n_output_value:
        return None
    return (f"recruit='novelty' has no effect on a route of {n_frames} frames with "
            f"{n_output}={n_output_value}: each frame gets its own unit, as with 'uniform'")
