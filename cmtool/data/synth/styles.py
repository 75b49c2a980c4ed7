"""City styles: the parameters that make the four procedural cities differ (modelled on nuPlan)."""

from __future__ import annotations

from dataclasses import asdict, dataclass


@dataclass(frozen=True)
class Style:
    block: tuple[float, float]  # block side range (m)
    rotation: float  # max |grid rotation| (degrees)
    jitter: float  # std of node jitter (m)
    warp: float  # amplitude of a smooth global warp that bends whole streets (m)
    warp_wavelength: float  # its wavelength (m)
    drop: float  # share of interior edges dropped (turns crossings into T-junctions)
    diagonals: int  # diagonal streets cutting across blocks
    curve_share: float  # share of roads given a lateral bend
    curve_amp: float  # bend amplitude as a fraction of the road length
    arterial_every: tuple[int, int]  # arterial spacing range in streets; (0, 0) = no arterials
    arterial_lanes: tuple[int, int]  # lanes per direction on arterials
    local_lanes: tuple[int, int]  # lanes per direction on other two-way streets
    one_way_lanes: tuple[int, int]  # lanes on one-way streets
    width: tuple[float, float]  # lane width range (m), drawn per street
    median: tuple[float, float]  # median width range on two-way arterials (m)
    one_way: float  # share of non-arterial streets that are one-way
    signal: float  # share of junctions (degree >= 3) with traffic lights
    crosswalk: float  # share of unsignalised junctions with crosswalks
    bus: float  # share of arterials whose outermost lanes are bus lanes

    def to_meta(self) -> dict:
        return {k: list(v) if isinstance(v, tuple) else v for k, v in asdict(self).items()}


STYLES = {
    # Las Vegas: straight regular grid, long blocks, wide 3+3 arterials, 2+2 elsewhere.
    "LAV": Style(
        block=(180.0, 260.0), rotation=0.0, jitter=1.0, warp=0.0,
        warp_wavelength=1000.0, drop=0.04, diagonals=0, curve_share=0.0, curve_amp=0.0,
        arterial_every=(2, 3), arterial_lanes=(3, 3), local_lanes=(2, 2), one_way_lanes=(2, 3),
        width=(3.4, 3.7), median=(0.0, 0.0), one_way=0.05, signal=0.9, crosswalk=0.3, bus=0.3,
    ),
    # Pittsburgh: rotated, jittered and bent grid, narrow 1+1 streets, many T-junctions.
    "PIT": Style(
        block=(90.0, 135.0), rotation=45.0, jitter=9.0, warp=22.0,
        warp_wavelength=480.0, drop=0.15, diagonals=0, curve_share=0.5, curve_amp=0.06,
        arterial_every=(0, 0), arterial_lanes=(1, 1), local_lanes=(1, 1), one_way_lanes=(1, 1),
        width=(3.0, 3.2), median=(0.0, 0.0), one_way=0.08, signal=0.55, crosswalk=0.3, bus=0.0,
    ),
    # Singapore: left-hand traffic (cmtool.maps.hdmap.LEFT_HAND), arterials with medians, mixed grid with
    # diagonal streets.
    "SGP": Style(
        block=(110.0, 170.0), rotation=30.0, jitter=4.0, warp=12.0,
        warp_wavelength=700.0, drop=0.1, diagonals=2, curve_share=0.15, curve_amp=0.04,
        arterial_every=(2, 4), arterial_lanes=(2, 3), local_lanes=(1, 2), one_way_lanes=(1, 2),
        width=(3.2, 3.5), median=(2.0, 5.0), one_way=0.1, signal=0.85, crosswalk=0.4, bus=0.3,
    ),
    # Boston: irregular old-city fabric, short blocks, many one-way streets.
    "BOS": Style(
        block=(60.0, 100.0), rotation=90.0, jitter=7.0, warp=22.0,
        warp_wavelength=380.0, drop=0.2, diagonals=1, curve_share=0.3, curve_amp=0.05,
        arterial_every=(5, 7), arterial_lanes=(2, 2), local_lanes=(1, 1), one_way_lanes=(1, 2),
        width=(3.0, 3.4), median=(0.0, 0.0), one_way=0.6, signal=0.6, crosswalk=0.6, bus=0.0,
    ),
}
