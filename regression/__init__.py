"""The regression model: the contract between training and the agent (paper II.D-E).

``model`` is the versioned model file (``CvvcModel``, ``ModelArrays``, ``features``); ``estimator`` evaluates
it, paper eq. (3)-(7), for one instant (the agent); ``batch`` applies the same functions to (T, ...) batches
(training statistics, the accuracy report). Imports only ``schemas`` (and numpy, msgspec).
"""
