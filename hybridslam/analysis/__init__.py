"""What users compute from a belief or a result: the paper's metrics (Sec. V), the marginals of
Eq. 6-8, trajectory errors (APE / RPE), consistency against ground truth, and plots."""
