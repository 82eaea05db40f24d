"""Linear algebra that knows nothing of peridynamics: sparse SPD solves with an adjoint
(``sparse``), assembly of Gram sums on a pattern (``assembly``, ``stiffness_solver``), factors
(``factors``), low-rank updates (``woodbury``), block half solves (``trailing``) and lock-step
batching of half solves (``lockstep``)."""
