"""The Foxglove layout of the live view (``data_samples/foxglove_layout.json``).

One step in Foxglove (Layouts -> Import from file) opens: the 3D scene (``/scene``, ``/tf``,
``/pose`` in frame ``O``), the tension plot (``/tensions/view``, one series per cable, with the
rig's limits from ``/tensions/limits``), the coefficient panel (the on-line reduction ``/online``:
CL, CD, Cm with their σ as a plot, and the whole message), and the event log (``/events``,
``/event``).  The file is in the layout format the Foxglove app exports (``configById``,
``layout``); its series name the cables of the rig, so ``python -m cdpr.daq.live_layout RIG.toml
> layout.json`` writes the layout of another rig.  A test checks that the sample file is this
module's output for the flat rigs and that every topic it names is one the live server serves.
"""

from __future__ import annotations

import json
import sys
import tomllib
from collections.abc import Sequence
from typing import Any

#: the panels' ids (type!id, as the app names them)
SCENE, TENSIONS, COEFFS, ONLINE, LOG = (
    "3D!cdpr-scene",
    "Plot!cdpr-tensions",
    "Plot!cdpr-coefficients",
    "RawMessages!cdpr-online",
    "RosOut!cdpr-events",
)


def _series(path: str, label: str, color: str | None = None) -> dict[str, Any]:
    s: dict[str, Any] = {
        "value": path,
        "enabled": True,
        "timestampMethod": "logTime",
        "label": label,
    }
    if color is not None:
        s["color"] = color
    return s


def foxglove_layout(
    cable_names: Sequence[str], target_O_m: Sequence[float] = (0.5, 0.0, 0.36)
) -> dict[str, Any]:
    """The layout for a rig with ``cable_names``; the 3D camera looks at ``target_O_m``."""
    plot_common = {
        "showXAxisLabels": True,
        "showYAxisLabels": True,
        "showLegend": True,
        "legendDisplay": "floating",
        "showPlotValuesInLegend": True,
        "isSynced": True,
        "xAxisVal": "timestamp",
        "followingViewWidth": 30,
        "sidebarDimension": 240,
    }
    tension_paths = [_series(f"/tensions/view.T_{c}_N", c) for c in cable_names]
    tension_paths += [
        _series("/tensions/limits.t_min_N", "t_min", "#1f5bff"),
        _series("/tensions/limits.t_max_N", "t_max", "#e00000"),
    ]
    coeff_paths = [_series(f"/online.{c}", c) for c in ("CL", "CD", "Cm")]
    coeff_paths += [_series(f"/online.sd_{c}", f"σ {c}") for c in ("CL", "CD", "Cm")]
    config = {
        SCENE: {
            "cameraState": {
                "perspective": True,
                "distance": 2.2,
                "phi": 60.0,
                "thetaOffset": 30.0,
                "targetOffset": [0.0, 0.0, 0.0],
                "target": [float(x) for x in target_O_m],
                "targetOrientation": [0.0, 0.0, 0.0, 1.0],
                "fovy": 45.0,
                "near": 0.01,
                "far": 100.0,
            },
            "followMode": "follow-none",
            "followTf": "O",
            "scene": {"enableStats": False},
            "transforms": {},
            "topics": {
                "/scene": {"visible": True},
                "/pose": {"visible": True, "type": "axis", "axisScale": 0.6},
            },
            "layers": {
                "grid": {
                    "visible": True,
                    "layerId": "foxglove.Grid",
                    "frameId": "O",
                    "size": 2.0,
                    "divisions": 20,
                    "lineWidth": 1.0,
                    "color": "#248eff40",
                    "position": [0.5, 0.0, 0.0],
                    "rotation": [0.0, 0.0, 0.0],
                    "order": 1,
                }
            },
            "publish": {
                "type": "point",
                "poseTopic": "",
                "pointTopic": "",
                "poseEstimateTopic": "",
            },
            "imageMode": {},
        },
        TENSIONS: {
            "title": "tensions (N) and the rig's limits",
            "paths": tension_paths,
            **plot_common,
        },
        COEFFS: {"title": "on-line coefficients (/online)", "paths": coeff_paths, **plot_common},
        ONLINE: {
            "topicPath": "/online",
            "diffEnabled": False,
            "diffMethod": "custom",
            "diffTopicPath": "",
            "showFullMessageForDiff": False,
            "expansion": "all",
        },
        LOG: {"searchTerms": [], "minLogLevel": 1, "topicToRender": "/events"},
    }
    layout = {
        "direction": "row",
        "first": SCENE,
        "second": {
            "direction": "column",
            "first": TENSIONS,
            "second": {
                "direction": "row",
                "first": {
                    "direction": "column",
                    "first": COEFFS,
                    "second": LOG,
                    "splitPercentage": 60,
                },
                "second": ONLINE,
                "splitPercentage": 55,
            },
            "splitPercentage": 45,
        },
        "splitPercentage": 50,
    }
    return {
        "configById": config,
        "globalVariables": {},
        "userNodes": {},
        "playbackConfig": {"speed": 1.0},
        "layout": layout,
    }


def layout_topics(layout: dict[str, Any]) -> set[str]:
    """Every topic a layout's panels read (``/a/b.field`` -> ``/a/b``)."""
    out: set[str] = set()
    for cfg in layout["configById"].values():
        for s in cfg.get("paths", []):
            out.add(s["value"].split(".", 1)[0])
        for key in ("topicPath", "topicToRender"):
            if key in cfg:
                out.add(cfg[key].split(".", 1)[0])
        out.update(cfg.get("topics", {}))
    return out


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m cdpr.daq.live_layout RIG.toml``: the layout of that rig on stdout."""
    from .schema import rig_from_mapping

    args = list(sys.argv[1:] if argv is None else argv)
    if len(args) != 1:
        print("usage: python -m cdpr.daq.live_layout RIG.toml > layout.json", file=sys.stderr)
        return 2
    with open(args[0], "rb") as fh:
        rig = rig_from_mapping(tomllib.load(fh), args[0])
    target = [float(rig.reference_position_O_m[0]), float(rig.reference_position_O_m[1]),
              float(rig.reference_position_O_m[2])]  # fmt: skip
    print(json.dumps(foxglove_layout(rig.cable_names, target), indent=2))
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
