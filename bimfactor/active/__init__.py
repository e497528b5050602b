"""Active localization: where to look next, from the belief's modes and the BIM (`suggest`)."""

from bimfactor.active.suggest import Hypothesis, Suggester, Suggestion, information_gain, path_views
from bimfactor.active.views import ViewPredictor

__all__ = ["Hypothesis", "Suggester", "Suggestion", "ViewPredictor", "information_gain", "path_views"]
