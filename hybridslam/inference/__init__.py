"""Building blocks shared by the estimators: Gauss-Newton updates (Eq. 9-11), association gating,
object creation on unknown maps, Laplace importance sampling, and batching over live slots."""
