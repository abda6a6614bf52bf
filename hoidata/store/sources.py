"""What a store's records come from, for its dataset card: each source dataset's licence, terms and citation.

A store names its source in its index (``provenance["source_dataset"]``, written by the build since the card
exists); older stores are named by their build's ``dataset.name``. The licence is the source's: a store holds
crops of its images, its labels and data derived from them (SDF samples, masks), plus MANO parameters and
simplified object meshes. Licence ids are the Hugging Face Hub's (``other`` where the terms are the dataset's own).
"""

from __future__ import annotations

from dataclasses import dataclass

MANO_CITATION = """@article{romero2017embodied,
  title = {Embodied Hands: Modeling and Capturing Hands and Bodies Together},
  author = {Romero, Javier and Tzionas, Dimitrios and Black, Michael J.},
  journal = {ACM Transactions on Graphics (Proc. SIGGRAPH Asia)},
  volume = {36},
  number = {6},
  year = {2017}
}"""

HOISDF_CITATION = """@inproceedings{qi2024hoisdf,
  title = {{HOISDF}: Constraining {3D} Hand-Object Pose Estimation with Global Signed Distance Fields},
  author = {Qi, Haozhe and Zhao, Chen and Salzmann, Mathieu and Mathis, Alexander},
  booktitle = {IEEE/CVF Conference on Computer Vision and Pattern Recognition (CVPR)},
  year = {2024}
}"""


@dataclass(frozen=True)
class Source:
    """One source dataset: ``license`` a Hub licence id; ``terms`` the licence in a sentence; ``shareable`` whether
    its terms let a derived store be published (``push_to_hub``) at all."""

    name: str
    homepage: str
    license: str
    license_name: str
    license_link: str
    terms: str
    shareable: bool
    citation: str
    made_with_mano: bool = True  # the store's MANO labels are parameters of the licensed MANO model


SOURCES = {
    "dexycb": Source(
        "DexYCB", "https://dex-ycb.github.io", "cc-by-nc-4.0", "CC BY-NC 4.0",
        "https://creativecommons.org/licenses/by-nc/4.0/",
        "Creative Commons Attribution-NonCommercial 4.0: share and adapt with attribution, no commercial use. The "
        "index's object meshes are simplified YCB models (CC BY 4.0).", True,
        """@inproceedings{chao2021dexycb,
  title = {{DexYCB}: A Benchmark for Capturing Hand Grasping of Objects},
  author = {Chao, Yu-Wei and Yang, Wei and Xiang, Yu and Molchanov, Pavlo and Handa, Ankur and Tremblay, Jonathan and
            Narang, Yashraj S. and Van Wyk, Karl and Iqbal, Umar and Birchfield, Stan and Kautz, Jan and Fox, Dieter},
  booktitle = {IEEE/CVF Conference on Computer Vision and Pattern Recognition (CVPR)},
  year = {2021}
}"""),
    "ho3d": Source(
        "HO-3D", "https://github.com/shreyashampali/ho3d", "other", "HO-3D terms of use",
        "https://github.com/shreyashampali/ho3d",
        "Academic, non-commercial research use only; the dataset may not be redistributed or modified without the "
        "authors' permission. The index's object meshes are simplified YCB models (CC BY 4.0).", False,
        """@inproceedings{hampali2020honnotate,
  title = {{HOnnotate}: A Method for {3D} Annotation of Hand and Object Poses},
  author = {Hampali, Shreyas and Rad, Mahdi and Oberweger, Markus and Lepetit, Vincent},
  booktitle = {IEEE/CVF Conference on Computer Vision and Pattern Recognition (CVPR)},
  year = {2020}
}"""),
    "hot3d_clips": Source(
        "HOT3D (HOT3D-Clips)", "https://facebookresearch.github.io/hot3d", "other", "HOT3D Dataset License Agreement",
        "https://www.projectaria.com/datasets/hot3d/license/",
        "Images and object annotations CC BY-SA; hand annotations CC BY-NC-SA (so a store holding both is "
        "non-commercial, share-alike); object models CC BY-SA without sale.", True,
        """@article{banerjee2024hot3d,
  title = {Introducing {HOT3D}: An Egocentric Dataset for {3D} Hand and Object Tracking},
  author = {Banerjee, Prithviraj and Shkodrani, Sindi and Moulon, Pierre and Hampali, Shreyas and Zhang, Fan and
            Fountain, Jade and Miller, Edward and Basol, Selen and Newcombe, Richard and Wang, Robert and
            Engel, Jakob Julian and Hodan, Tomas},
  journal = {arXiv preprint arXiv:2406.09598},
  year = {2024}
}"""),
    "unknown": Source(
        "not recorded in this store", "", "other", "the source dataset's", "",
        "The store does not say which dataset its records come from (rerun `hoidata card STORE --source NAME`); its "
        "licence is that dataset's: check it before sharing.", False, ""),
    "toy": Source(
        "hoidata toy data (procedural, written by hoidata make-toy)", "https://github.com/amathislab/HOISDF", "mit",
        "MIT", "https://opensource.org/license/mit",
        "Made by the project's own code (a procedural hand, objects and scenes): no third-party data, MIT like the "
        "code.", True, "", made_with_mano=False),
}
TOY_MARKER = ".hoidata-toy.json"  # make-toy's mark on a dataset folder it wrote: a build from it is a toy store


def source_of(index_config: dict, provenance: dict) -> str:
    """The id in :data:`SOURCES` of a store's source: its provenance's ``source_dataset`` (a synthetic store: its
    source store's), else its build's ``dataset.name``, else "unknown"."""
    dataset = index_config.get("dataset")
    name = provenance.get("source_dataset") or (dataset.get("name") if isinstance(dataset, dict) else None)
    return name if name in SOURCES else "unknown"
