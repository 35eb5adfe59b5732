"""Named PEMs: how ``pemviz pem train --model NAME`` (re)trains each shipped PEM: ``ml-nn`` (the paper's ML-NN,
Innes & Ramamoorthy (2022), Table I), ``gbt`` (gradient-boosted trees, the best by pemviz's 5-fold cross-validation)
and the noise PEM ``hetero-t`` (a heteroscedastic Student-t, chosen by cross-validated NLL), in ``pemviz/assets/``.
``seed`` is the shipped weights'; ``pemviz/assets/README.md`` says why each was chosen."""

from __future__ import annotations

from pemviz.pem.noise import NoiseRecipe
from pemviz.pem.training import PemRecipe
from pemviz.pem.trees import TreeRecipe

DEFAULT_PEM_NAME = "ml-nn"
"""The PEM :func:`pemviz.pem.load_pem` loads when given no name."""
BEST_PEM_NAME = "gbt"
"""The best cross-validated PEM (by 5-fold cross-validated BCE and ROC-AUC)."""
DEFAULT_NOISE_NAME = "hetero-t"
"""The noise PEM :func:`pemviz.pem.load_noise_pem` loads when given no name."""


PEM_RECIPES: dict[str, PemRecipe | TreeRecipe] = {
    "ml-nn": PemRecipe(
        name="ml-nn",
        description="the paper's ML-NN: 14-20-20-1 with BatchNorm, Adam 1e-3, batch 1024, 300 epochs",
        seed=2,
    ),
    "gbt": TreeRecipe(
        name="gbt",
        description="gradient-boosted trees (scikit-learn HistGradientBoosting) on the same 14 features: "
        "300 trees of 63 leaves, learning rate 0.05, L2 1.0",
    ),
}
"""Named PEMs that ``pemviz pem train --model NAME`` can (re)train."""


NOISE_RECIPES: dict[str, NoiseRecipe] = {
    "hetero-t": NoiseRecipe(
        name="hetero-t",
        description="heteroscedastic noise PEM: 14-32-32-4 ReLU network -> Student-t location and log scale per "
        "dimension (range, lateral), one learned degrees of freedom each; Adam 3e-3, batch 512, 100 epochs",
    ),
}
"""Named noise PEMs that ``pemviz pem train --model NAME`` can (re)train."""
