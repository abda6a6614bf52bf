"""The procedural toy datasets: DexYCB and HO-3D v2 trees in the real on-disk layouts, written from the toy hand
and objects (``hoidata make-toy``; :mod:`hoidata.toy.make`). They sit above the readers, the pipeline and the
grasp synthesis they use; nothing below imports them."""
