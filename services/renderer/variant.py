"""Choose the Mitsuba variant: the JIT ``llvm_ad_rgb`` when a usable libLLVM exists, else scalar.

Dr.Jit's LLVM backend needs LLVM >= 16 here (Debian's LLVM 15 crashes it, which cannot be caught),
so ``auto`` only picks LLVM when it finds such a library or ``DRJIT_LIBLLVM_PATH`` names one.
"""

from __future__ import annotations

import glob
import os
import re
from dataclasses import dataclass
from typing import Literal

__all__ = ["LLVM_VARIANT", "SCALAR_VARIANT", "VariantChoice", "choose_variant", "find_libllvm"]

LLVM_VARIANT = "llvm_ad_rgb"
SCALAR_VARIANT = "scalar_rgb"
MIN_LLVM_MAJOR = 16
_PATTERNS = (
    "/usr/lib/*/libLLVM.so.*",
    "/usr/lib/*/libLLVM-*.so",
    "/usr/lib/llvm-*/lib/libLLVM*.so*",
    "/usr/lib64/libLLVM*.so*",
    "/usr/local/lib/libLLVM*.so*",
)

VariantRequest = Literal["auto", "llvm_ad_rgb", "scalar_rgb"]


@dataclass(frozen=True)
class VariantChoice:
    """The variant to set and, for LLVM, the library Dr.Jit should load."""

    variant: str
    libllvm: str | None
    reason: str


def _major_version(path: str) -> int | None:
    match = re.search(r"(?:llvm-|libLLVM[.-]|libLLVM\.so\.)(\d+)", path)
    return int(match.group(1)) if match else None


def find_libllvm() -> str | None:
    """Path of the newest libLLVM >= 16 on this machine, or ``DRJIT_LIBLLVM_PATH`` if it exists."""
    configured = os.environ.get("DRJIT_LIBLLVM_PATH")
    if configured and os.path.isfile(configured):
        return configured
    found: list[tuple[int, str]] = []
    for pattern in _PATTERNS:
        for path in glob.glob(pattern):
            major = _major_version(path)
            if major is not None and major >= MIN_LLVM_MAJOR and os.path.isfile(path):
                found.append((major, path))
    return max(found)[1] if found else None


def choose_variant(requested: VariantRequest) -> VariantChoice:
    """Resolve the configured variant; an explicit LLVM request without libLLVM is an error."""
    if requested == SCALAR_VARIANT:
        return VariantChoice(SCALAR_VARIANT, None, "configured")
    library = find_libllvm()
    if library is not None:
        return VariantChoice(LLVM_VARIANT, library, f"libLLVM found at {library}")
    if requested == LLVM_VARIANT:
        raise RuntimeError(
            f"COSMOS_RENDERER_MITSUBA_VARIANT={LLVM_VARIANT} but no libLLVM >= "
            f"{MIN_LLVM_MAJOR} was found; "
            "install it (apt-get install libllvm19) or set DRJIT_LIBLLVM_PATH"
        )
    return VariantChoice(SCALAR_VARIANT, None, f"no libLLVM >= {MIN_LLVM_MAJOR} found")
