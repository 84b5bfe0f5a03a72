"""ReSiReg: spatially consistent dense vision-language features (method, encoders, inference)."""

from resireg.heuristic import PrototypeHeuristic
from resireg.reconstruct import ReSiRegFull, ReSiRegLite
from resireg.variants import VARIANTS, build_variant

__all__ = ["ReSiRegFull", "ReSiRegLite", "PrototypeHeuristic", "VARIANTS", "build_variant"]
__version__ = "0.1.0"
