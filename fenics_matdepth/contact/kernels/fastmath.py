"""The floating-point licence of the contact kernels (one setting, shared by their modules)."""

from __future__ import annotations

__all__ = ["FMA"]

#: Floating-point licence of the pair kernels: "contract" lets LLVM fuse a multiplication and
#: an addition into one fused multiply-add (one rounding instead of two); with it the Hessian
#: pass takes about 0.81 of the time it takes without (docs/kernels.md). No other fast-math
#: licence: NaN and inf propagate and sums keep their order. The clip (geometry/clip.py), whose
#: signs decide which pairs intersect, is compiled without it.
FMA = {"contract"}
