"""The reports: evaluation of a split, metrics, statistics over training seeds,
comparisons of methods, figures and the crop-premise diagnosis."""
