"""ReSiReg: spatially consistent dense vision-language features (method and inference)."""

from resireg.heuristic import PrototypeHeuristic
from resireg.reconstruct import ReSiRegFull, ReSiRegLite

__all__ = ["ReSiRegFull", "ReSiRegLite", "PrototypeHeuristic"]
__version__ = "0.1.0"
