"""Every figure of implantplan, one module per stage, used by the commands and by ``plan``/the
report (DESIGN.md section 2: figures never import a command module).

- ``fpsm``: the mouth opening and the FPSM fit (stage 1);
- ``placement``: instrument placement and the virtual fixture per site (stage 2);
- ``robot``: MOPRP Pareto sets and the selected layout, PNG and Meshcat HTML (stage 3);
- ``capability``: capability map slices and RASSCMAP setups (stage 4, ``capmap``);
- ``simulation``: the teleop feeding, error-mapping and layout experiments (stage 5);
- ``plan``: every figure of a case plan, by report section.
"""

from __future__ import annotations

from pathlib import Path


def save(fig, path, *, dpi: int, tight: bool = True) -> Path:
    """Lay out (``tight``), write (its folder made) and close a matplotlib figure; the path."""
    import matplotlib.pyplot as plt

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    if tight:
        fig.tight_layout()
    fig.savefig(path, dpi=dpi)
    plt.close(fig)
    return path
