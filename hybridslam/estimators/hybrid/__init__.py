"""The hybrid belief of Tchuiev, Feldman & Indelman (IROS 2019): weighted Gaussian components
indexed by (class realization C, association history β_1:k), advanced by Algorithm 1."""
