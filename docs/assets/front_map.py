"""Draws ``front_map.png``, the README's picture, from a finished run with the report's own
plot of the fused map (:func:`como3r.evaluation.plot_map.map_figure`).

Made from the demo::

    como3r demo --out /tmp/docs/demo_out
    python docs/assets/front_map.py /tmp/docs/demo_out/run docs/assets/front_map.png
"""

from __future__ import annotations

import io
import sys
from pathlib import Path

from PIL import Image

from como3r.evaluation.plot_map import map_figure, sample_map
from como3r.evaluation.report_data import load_run

#: points drawn, the figure's resolution and its colours: small enough for a README (< 200 kB)
POINTS, DPI, COLOURS = 20_000, 80, 256


def main(run_dir: Path, out: Path) -> None:
    sample = sample_map(run_dir / "map.ply", max_points=POINTS)
    if sample is None:
        raise SystemExit(f"{run_dir}: no map.ply to draw")
    figure = map_figure(sample, load_run(run_dir).tracks)
    buffer = io.BytesIO()
    figure.savefig(buffer, format="png", dpi=DPI)
    image = Image.open(buffer).convert("RGB").quantize(COLOURS, method=Image.Quantize.FASTOCTREE)
    image.save(out, optimize=True)


if __name__ == "__main__":
    main(Path(sys.argv[1]), Path(sys.argv[2]))
