"""Loop closure: late objects merged with old ones, after a run or during it.

* :mod:`.closure`: the pass over a finished run (:func:`~.closure.close_loops`), split by idea:
  settings and report in :mod:`.settings`, the candidate search and its Bayes factor in
  :mod:`.search`, the re-solve and verification in :mod:`.verify`, the negative information of
  objects in view yet undetected in :mod:`.misses`, the object bookkeeping (merges, re-opening) in
  :mod:`.merge`;
* :mod:`.online`: the same search between the steps of a run, its merges added as hypotheses
  (:class:`~.online.OnlineLoopClosure`); what it needs of an estimator is the estimators' base's
  ``LoopClosureAccess``, which the hybrid belief and ``multimodal`` give in their own ``loops``
  modules.
"""
