"""cmtool: controllable lane-level HD map generation from SD maps (ControlMap).

Pipeline (one subpackage per stage): ``data`` (maps, scenes, rasters, dataset cache) ->
model -> sample -> eval -> ``viz`` (pictures and Rerun recordings). ``cli`` wires them to the
``cmtool`` command.
"""

__version__ = "0.1.0"
