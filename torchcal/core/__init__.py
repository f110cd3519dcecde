"""The lowest floor: small shared types and helpers every other layer may use, and that use none of them.

Errors (:mod:`~torchcal.core.exceptions`), units (:mod:`~torchcal.core.units`: mm/deg at the boundary,
SI inside), CPU threads (:mod:`~torchcal.core.threads`), progress tasks (:mod:`~torchcal.core.progress`),
a measurement set (:mod:`~torchcal.core.measurements`), direction coverage (:mod:`~torchcal.core.coverage`),
the Chebyshev basis (:mod:`~torchcal.core.basis`), parameter kinds (:mod:`~torchcal.core.params`), the
Gamma law of residual norms (:mod:`~torchcal.core.gamma_fit`) and the model contract
(:mod:`~torchcal.core.contract`). This package imports none of them itself: ``import torchcal`` must stay
light (torch loads when a function needs it).
"""
