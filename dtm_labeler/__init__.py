"""dtm_labeler: body-part labeling of unlabeled 3-D marker clouds.

Method: Hu & Wong, "Labeling of Human Motion Based on CBGA and Probabilistic Model"
(decomposable triangulated model + per-triangle Gaussian mixtures chosen by MDL +
constraint-based genetic algorithm). The algorithmic core has no ROS imports; the
ROS 2 node and bag tools live in :mod:`dtm_labeler.ros`.
"""

import os as _os

# The numerical work here is many small matrices per frame; multi-threaded BLAS only adds
# wake-up latency and fights the node's own threads on small machines. Respect a user setting.
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    _os.environ.setdefault(_var, "1")

__version__ = "0.1.0"
