"""``train.precision``: fp32, bf16 autocast, or ``auto``: bf16 where the device computes it natively and a test block
runs faster in it, said in one line with the reason."""

from __future__ import annotations

import time
from pathlib import Path

import torch

NATIVE_FLAGS = {"amx_bf16": "AMX-BF16", "avx512_bf16": "AVX512-BF16"}  # CPU flags of bf16 arithmetic in hardware
MIN_SPEEDUP = 1.1  # bf16 must beat fp32 on the test block by this much; a closer call is measurement noise
BLOCK = {"cpu": (256, 512), "cuda": (1024, 8192)}  # test block per device type: width, tokens
PAIRS = 3  # timed passes per precision, after one to warm up


def cpu_bf16_flags(cpuinfo: str | Path = "/proc/cpuinfo") -> set[str]:
    """Which of :data:`NATIVE_FLAGS` this CPU has: from the flags of ``cpuinfo``, or where it has none (not Linux,
    not x86), from torch's own checks."""
    try:
        flags = next(line for line in Path(cpuinfo).read_text().splitlines() if line.startswith("flags"))
        return set(flags.partition(":")[2].split()) & NATIVE_FLAGS.keys()
    except (OSError, UnicodeDecodeError, StopIteration):
        checks = {"avx512_bf16": "_is_avx512_bf16_supported", "amx_bf16": "_is_amx_tile_supported"}
        return {flag for flag, name in checks.items() if getattr(torch.cpu, name, lambda: False)()}


def cpu_has_native_bf16() -> bool:
    """Whether this CPU computes bf16 natively (AVX512-BF16 or AMX), where bf16 autocast speeds training up."""
    return bool(cpu_bf16_flags())


def native_bf16(device: torch.device, flags: set[str] | None = None) -> tuple[bool, str]:
    """Whether ``device`` computes bf16 natively, and why (``flags``: the CPU's, :func:`cpu_bf16_flags` when None)."""
    if device.type == "cuda":
        major, minor = torch.cuda.get_device_capability(device)
        return major >= 8, f"CUDA {major}.{minor} {'computes bf16 natively' if major >= 8 else 'lacks native bf16'}"
    if device.type == "cpu":
        flags = cpu_bf16_flags() if flags is None else flags
        names = [NATIVE_FLAGS[f] for f in NATIVE_FLAGS if f in flags]
        return bool(names), f"CPU has {' and '.join(names)}" if names else "CPU lacks native bf16"
    return False, f"{device.type}: no check of native bf16"


def time_block(device: torch.device) -> tuple[float, float]:
    """Seconds of a forward and backward pass of a transformer MLP block in fp32 and under bf16 autocast (the best of
    :data:`PAIRS` each, interleaved). On a CPU on one thread, in that thread's CPU time: other work on the machine
    does not move the comparison. The global random state is left as it was."""
    width, tokens = BLOCK[device.type]
    cpu = device.type == "cpu"
    clock = time.thread_time if cpu else time.perf_counter
    threads = torch.get_num_threads()
    best = {False: float("inf"), True: float("inf")}
    with torch.random.fork_rng(devices=[] if cpu else [device]):
        torch.manual_seed(0)
        block = torch.nn.Sequential(torch.nn.Linear(width, 4 * width), torch.nn.GELU(),
                                    torch.nn.Linear(4 * width, width)).to(device)
        x = torch.randn(tokens, width, device=device)
        if cpu:
            torch.set_num_threads(1)
        try:
            for k in range(PAIRS + 1):
                for bf16 in (False, True):
                    if not cpu:
                        torch.cuda.synchronize(device)
                    start = clock()
                    with torch.autocast(device.type, dtype=torch.bfloat16, enabled=bf16):
                        y = block(x)
                    y.float().square().mean().backward()
                    if not cpu:
                        torch.cuda.synchronize(device)
                    if k:  # the first pair warms up
                        best[bf16] = min(best[bf16], clock() - start)
        finally:
            torch.set_num_threads(threads)
    return best[False], best[True]


def auto_choice(native: bool, why: str, timings: tuple[float, float] | None = None) -> tuple[bool, str]:
    """``auto``'s choice from whether the device computes bf16 natively (``why``: what it has) and, where it does,
    the seconds of the test block in fp32 and bf16; and the line that says it."""
    if not native:
        return False, f"precision auto: fp32 ({why})"
    fp32_s, bf16_s = timings
    speedup = fp32_s / max(bf16_s, 1e-12)
    if speedup >= MIN_SPEEDUP:
        return True, f"precision auto: bf16 ({why}; {speedup:.1f}x faster on a test block)"
    return False, f"precision auto: fp32 ({why}, but bf16 was not faster on a test block: {speedup:.2f}x)"


def resolve(setting: str, device: torch.device, kept: str | None = None) -> tuple[bool, str]:
    """Whether ``setting`` (train.precision) trains in bf16 on ``device``, and a line to print ("" for none): why
    ``auto`` chose, or that bf16 would be emulated. ``kept``: the precision a resumed run trained in so far, which
    ``auto`` keeps (a resumed run computes as the uninterrupted one)."""
    if setting == "auto":
        if kept in ("bf16", "fp32"):
            return kept == "bf16", f"precision auto: {kept} (kept: the run trained in it so far)"
        native, why = native_bf16(device)
        return auto_choice(native, why, time_block(device) if native else None)
    bf16 = setting == "bf16"
    if bf16 and device.type == "cpu" and not cpu_has_native_bf16():
        return True, ("warning: train.precision bf16 on a CPU without native bf16 (AVX512-BF16 or AMX): autocast "
                      "emulates it, many times slower than fp32; give --precision fp32")
    return bf16, ""
