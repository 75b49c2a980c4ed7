"""SD ways offset by their lane counts with no junctions at all (the rules' lanes without setbacks or connectors),
scored against a dataset's ground truth: the reference of docs/baselines.md. Usage:
python docs/offset_layout.py out/av2_exact"""

import sys

import numpy as np

import cmtool.data.rules as rules
from cmtool.data.cache import load_dataset
from cmtool.data.layouts import scene_layouts
from cmtool.metrics.lanes import lane_scores

rules._setbacks = lambda edges, *rest: [(0.0, 0.0)] * len(edges)  # lanes run on to the nodes
rules._connect = lambda *rest: None  # and nothing joins them there
data = load_dataset(sys.argv[1], "test")
scenes = [data.scene(i) for i in range(min(96, len(data)))]
layouts = scene_layouts(sys.argv[1], "test", scenes, "rules")
f1 = np.array([lane_scores(m.to_lanegraph(neighbours=False).lanes, s.to_lanegraph(neighbours=False).lanes)["f1"]
               for m, s in zip(layouts, scenes)])
junction = np.array([s.kind.startswith("junction") for s in scenes])
print(f"lane F1 at 1 m: all {f1.mean():.3f}, junction frames {f1[junction].mean():.3f}, others {f1[~junction].mean():.3f}")
