"""The GTSAM pose-graph backend: Sim(3)/SE(3)/SE(2) graphs on iSAM2 with PCM / GNC loop outlier rejection.

``posegraph`` (Protocol + ``GtsamPoseGraph`` + ``BACKENDS`` registry), ``pcm`` (pairwise consistency),
``lie`` (group adapters, matrix and covariance layouts), ``graph_io`` (g2o / TORO / city10000 in,
g2o out), ``simulate`` (monocular drift problems from GT trajectories), ``experiment`` (run + evo
ATE), ``plot``, ``cli`` (``symbio posegraph``).
"""
