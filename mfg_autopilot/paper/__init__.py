"""The paper's algorithms as the paper writes them (Shiri, Park, Bennis; SPEC errata applied).

Parameters (:mod:`.params`), the feature maps sigma_H / sigma_F (:mod:`.features`), the
model of eq. 9 and the optimal action of eq. 8 (:mod:`.model`), the costs phi_L, phi_G of
eq. 3 (:mod:`.costs`), the HJB and FPK learners of Algorithms 3 and 4 (:mod:`.learners`,
:mod:`.meanfield`), their numba kernels (:mod:`.kernels`), and the `paper` preset's controller
banks (:mod:`.controllers`). Pure numerics, no I/O. May import only :mod:`mfg_autopilot.interface`
and third-party numerics (numpy, scipy, numba); nothing from guidance, safety, pde, mission
or runtime.
"""
