"""The export formats, one table: the command's choices and help are made from it (a format added here is listed)."""

FORMATS = {  # name -> the consumers that read it
    "handoccnet": "HandOccNet, H2ONet, HandBooster (DEX_YCB.py / HO3D.py annotation files)",
    "gsdf": "gSDF, AlignSDF (annotations, split lists, SDF files, test meshes)",
}
DATASETS = {"handoccnet": ("dexycb", "ho3d"), "gsdf": ("dexycb",)}  # gSDF has no HO-3D dataset class
