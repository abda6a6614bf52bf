"""The procedural toy world: a hand in the exact MANO file format (:mod:`hoidata.toy.hand`, its mesh in
:mod:`hoidata.toy.hand_mesh`), YCB-layout stand-in objects (:mod:`hoidata.toy.objects`), and DexYCB and HO-3D trees
in the real on-disk layouts written from them (``hoidata make-toy``; :mod:`hoidata.toy.make`), a recipe on the engine
(:class:`hoidata.toy.dexycb.ToyTask`, one :class:`~hoidata.toy.dexycb.ToyJob` per sequence). They sit above the
readers, the engine and the grasp synthesis they use; no other recipe and nothing below imports them."""
