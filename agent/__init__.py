"""The online controller: aligner, controller, CVVC problem and solve, eq. 8 set points, runtime (paper II.E, III)."""
