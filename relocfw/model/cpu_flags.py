"""What the CPU can do, for choices that depend on it (int8 weights' width, benchmarks)."""

from __future__ import annotations

import platform
from pathlib import Path

# Instructions that multiply u8 x s8 and accumulate in 32 bits, without AVX2's
# 16-bit intermediate (vpmaddubsw) that 8-bit weights can saturate.
VNNI_FLAGS = ("avx512_vnni", "avx_vnni", "amx_int8")


def cpu_flags(cpuinfo: Path = Path("/proc/cpuinfo")) -> set[str] | None:
    """The first CPU's feature flags from `cpuinfo` (Linux), None when they cannot be
    read (another OS, or a file without a flags line)."""
    try:
        text = cpuinfo.read_text()
    except OSError:
        return None
    lines = [line for line in text.splitlines() if line.startswith("flags")]
    return set(lines[0].split(":", 1)[1].split()) if lines else None


def is_x86() -> bool:
    """Whether this is an x86 CPU (where VNNI decides; other CPUs have no such flag)."""
    return platform.machine().lower() in ("x86_64", "amd64", "i386", "i686", "x86")


def int8_saturation_reason(cpuinfo: Path = Path("/proc/cpuinfo")) -> str | None:
    """Why onnxruntime's u8 x s8 products may saturate on this CPU with 8-bit weights;
    None when they cannot (VNNI, or not x86: arm64's dot products accumulate in 32
    bits). onnxruntime's documentation advises 7-bit weights (reduce_range) there."""
    if not is_x86():
        return None
    flags = cpu_flags(cpuinfo)
    if flags is None:
        return (
            f"relocfw cannot read this CPU's flags (no flags line in {cpuinfo}) to tell "
            "whether it has VNNI, without which 8-bit weights saturate; use "
            "onnx.int8=static (7-bit weights)"
        )
    if flags & set(VNNI_FLAGS):
        return None
    return (
        "this CPU has no VNNI (AVX-512 VNNI / AVX-VNNI): its u8 x s8 products saturate "
        "with 8-bit weights; use onnx.int8=static (7-bit weights)"
    )
