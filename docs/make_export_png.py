"""docs/export.png: what `mapkit export-foxglove` wrote for the sample forest, drawn from the MCAP
itself (read back with the `mcap` reader and the file's own protobuf schemas), since Foxglove has no
headless renderer. Run after `make demo`:

    .venv/bin/python docs/make_export_png.py [demo_ws/forest.mcap]
"""

from __future__ import annotations

import sys
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
from mcap.reader import make_reader
from mcap_protobuf.decoder import DecoderFactory

REPO = Path(__file__).resolve().parent.parent


def main() -> None:
    path = Path(sys.argv[1]) if len(sys.argv) > 1 else REPO / "demo_ws" / "forest.mcap"
    messages: dict[str, list] = {}
    with open(path, "rb") as f:
        for _, channel, _, decoded in make_reader(f, decoder_factories=[DecoderFactory()]).iter_decoded_messages():
            messages.setdefault(channel.topic, []).append(decoded)
    fig, (top, depth) = plt.subplots(1, 2, figsize=(11, 4.6), gridspec_kw={"width_ratios": [1.6, 1]})
    grid = messages["/map/esdf_slices"][len(messages["/map/esdf_slices"]) // 2]
    cells = np.frombuffer(grid.data, dtype=[("distance", "<f4"), ("observed", "u1")]).reshape(-1, grid.column_count)
    x0, y0, s = grid.pose.position.x, grid.pose.position.y, grid.cell_size.x
    extent = (x0, x0 + s * cells.shape[1], y0, y0 + s * cells.shape[0])
    image = top.imshow(np.clip(cells["distance"], -1, 3), origin="lower", extent=extent, cmap="RdBu", vmin=-3, vmax=3)
    fig.colorbar(image, ax=top, label=f"ESDF at z = {grid.pose.position.z:.1f} m [m] (/map/esdf_slices)")
    cloud = messages["/map/cloud"][0]
    points = np.frombuffer(cloud.data, dtype=[("xyz", "<f4", 3), ("rgba", "u1", 4)])
    points = points[points["xyz"][:, 2] > 0.3][::3]  # the ground would cover the map
    top.scatter(points["xyz"][:, 0], points["xyz"][:, 1], s=0.3, c=points["rgba"] / 255.0, label="/map/cloud (above 0.3 m)")
    body = np.array([[t.transforms[0].translation.x, t.transforms[0].translation.y] for t in messages["/tf"]])
    top.plot(body[:, 0], body[:, 1], "k-", lw=1.5, zorder=5, label="/tf world → body")
    for update in messages.get("/planner/plans", []):
        entity = update.entities[0]
        line = np.array([[p.x, p.y] for p in entity.lines[0].points])
        top.plot(line[:, 0], line[:, 1], "-", color="tab:green", lw=1.5, zorder=6)
        kp = np.array([[sp.pose.position.x, sp.pose.position.y] for sp in entity.spheres])
        top.plot(kp[:, 0], kp[:, 1], "o", color="tab:orange", ms=3, zorder=7)
    top.plot([], [], "-", color="tab:green", label="/planner/plans (key-points orange)")
    top.set(xlim=extent[:2], ylim=extent[2:], xlabel="x (m)", ylabel="y (m)", aspect="equal",
            title=f"{path.name}: top view")
    top.legend(loc="lower left", fontsize=7, markerscale=8)
    frame = messages["/camera/depth"][len(messages["/camera/depth"]) // 2]
    mm = np.frombuffer(frame.data, dtype="<u2").reshape(frame.height, frame.width)
    shown = depth.imshow(np.where(mm > 0, mm / 1000.0, np.nan), cmap="viridis")
    fig.colorbar(shown, ax=depth, label="depth [m] (/camera/depth, 16UC1 mm)")
    depth.set(title="/camera/depth, middle frame", xticks=[], yticks=[])
    fig.tight_layout()
    out = REPO / "docs" / "export.png"
    fig.savefig(out, dpi=110)
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
