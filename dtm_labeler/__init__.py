"""dtm_labeler: body-part labeling of unlabeled 3-D marker clouds.

Method: Hu & Wong, "Labeling of Human Motion Based on CBGA and Probabilistic Model"
(decomposable triangulated model + per-triangle Gaussian mixtures chosen by MDL +
constraint-based genetic algorithm). The algorithmic core has no ROS imports; the
ROS 2 node and bag tools live in :mod:`dtm_labeler.ros`.
"""

__version__ = "0.1.0"
