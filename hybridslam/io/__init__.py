"""Files: scenario and result files (``hybridslam-scenario/1``, ``hybridslam-result/2`` and ``/1``; see
``docs/file_format.md``) and importers of public datasets. Pure numpy and the standard library."""
