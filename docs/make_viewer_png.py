"""Make docs/viewer.png: `mapkit view` on a sample workspace with a live plan, captured in headless
Chromium (the same route as tests/test_viewer_browser.py).

    .venv/bin/python docs/make_viewer_png.py -w demo_ws/forest --model demo_ws/forest/runs/demo

The camera sits behind and above the selected frame's body, looking along its heading (viser's
``initialCameraPosition`` / ``initialCameraLookAt`` URL parameters); the goal is `--ahead` metres in
front of it, `--left` to the side.
"""

from __future__ import annotations

import argparse
import io
from pathlib import Path

import numpy as np


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("-w", "--workspace", type=Path, required=True)
    ap.add_argument("--model", type=Path, required=True)
    ap.add_argument("--frame", type=int, default=150)
    ap.add_argument("--ahead", type=float, default=7.0)
    ap.add_argument("--left", type=float, default=1.5)
    ap.add_argument("--corridor", type=float, default=0.4)
    ap.add_argument("-o", "--output", type=Path, default=Path(__file__).with_name("viewer.png"))
    args = ap.parse_args()

    from PIL import Image

    from mapkit.ingest import open_frames_store
    from mapkit.viewer import ViewerApp, ViewerConfig, screenshot

    T_wb = open_frames_store(args.workspace).T_world_body[args.frame]
    p, fwd = T_wb[:3, 3], T_wb[:3, 0]
    left = np.cross([0.0, 0.0, 1.0], fwd)
    goal = p + args.ahead * fwd + args.left * left
    config = ViewerConfig(workspace=args.workspace, model=args.model, port=0, frame=args.frame,
                          goal=tuple(float(v) for v in goal), corridor=args.corridor)
    with ViewerApp(config) as app:
        eye = p - 7.0 * fwd - 3.0 * left + np.array([0.0, 0.0, 6.5])
        look = p + 4.0 * fwd
        query = (f"?initialCameraPosition={','.join(f'{v:.2f}' for v in eye)}"
                 f"&initialCameraLookAt={','.join(f'{v:.2f}' for v in look)}")
        raw = args.output.with_suffix(".raw.png")
        screenshot(app.url + query, raw, width=1500, height=1000)
    # keep full colour when it fits the README's 1 MB budget, else a 256-colour palette
    buf = io.BytesIO()
    Image.open(raw).convert("RGB").save(buf, format="PNG", optimize=True)
    if buf.tell() > 900_000:
        buf = io.BytesIO()
        img = Image.open(raw).convert("RGB").quantize(colors=256, method=Image.Quantize.FASTOCTREE,
                                                      dither=Image.Dither.NONE)
        img.save(buf, format="PNG", optimize=True)
    args.output.write_bytes(buf.getvalue())
    raw.unlink()
    print(f"wrote {args.output} ({len(buf.getvalue()) / 1e3:.0f} kB); η and latency: see the panel")


if __name__ == "__main__":
    main()
