"""Object labels from IFC texts: rules (English, German, IFC types), type siblings, embedding, IFC class."""

from __future__ import annotations

import numpy as np
import pytest

from bimfactor.bim.ifc import IfcElement
from bimfactor.bim.vocabulary import LabelSource, Vocabulary, label_elements, normalise
from bimfactor.config import config_file
from bimfactor.embed.text import MiniLMTextEmbedder


@pytest.fixture(scope="module")
def vocabulary() -> Vocabulary:
    return Vocabulary.load(config_file("vocabulary.yaml"))


def element(
    ifc_class: str = "IfcFurniture", name: str = "", type_name: str = "", predefined: str = "", type_class: str = ""
) -> IfcElement:
    ancestry = {
        "IfcFurniture": ("IfcFurniture", "IfcFurnishingElement", "IfcElement"),
        "IfcWindow": ("IfcWindow", "IfcBuildingElement", "IfcElement"),
        "IfcFlowTerminal": ("IfcFlowTerminal", "IfcDistributionFlowElement", "IfcElement"),
        "IfcStair": ("IfcStair", "IfcBuildingElement", "IfcElement"),
    }[ifc_class]
    type_class = type_class or ("IfcFurnitureType" if type_name else "")
    return IfcElement("g", ifc_class, ancestry, name, "", type_name, type_class, predefined, "", 0, None)


def test_normalise_spells_out_umlauts_and_separators() -> None:
    assert normalise("Küchen_Schrank-1:Tür") == "kuechen schrank 1 tuer"
    assert normalise("  M_Table-Coffee:0610 x 0610 ") == "m table coffee 0610 x 0610"


@pytest.mark.parametrize(
    ("text", "label"),
    [
        ("Stuhl", "chair"),
        ("Schreibtisch", "desk"),
        ("Doppelbett", "bed"),
        ("Buerotisch", "desk"),
        ("Labortisch", "lab bench"),
        ("Kuechenschrank 4", "cabinet"),
        ("Waschbecken-1", "sink"),
        ("Badewanne", "bathtub"),
        ("Duschwanne", "shower"),
        ("WC", "water closet"),
        ("TOILETPAN", "water closet"),
        ("WASHHANDBASIN", "sink"),
        ("Sessel", "armchair"),
        ("Furniture_Couch_Viper:2290x950", "sofa"),
        ("M_Table-Coffee:0610 x 0610 x 0", "coffee table"),
        ("Furniture_Table_Dining_w-Chair", "dining table"),
        ("M_Counter Top w Sink Hole:600m", "sink"),
        ("M_Base Cabinet-Double Door & 2", "cabinet"),
        ("1525 x 2007mm - Queen", "bed"),
        ("Fire hydrant", "fire hydrant"),
        # offices, institutes, building services (IFC predefined types included)
        ("Heizkörper 22-600", "radiator"),
        ("PANELRADIATOR", "radiator"),
        ("BASEBOARDHEATER", "radiator"),
        ("Warmwasserspeicher", "boiler"),
        ("Whiteboard 2000", "whiteboard"),
        ("Wandtafel", "whiteboard"),
        ("Laserdrucker", "printer"),
        ("Spindschrank 4-tuerig", "locker"),
        ("Steel Shelves 900", "bookshelf"),
        ("Aktenschrank", "cabinet"),
        ("Feuerloescher 6kg", "fire extinguisher"),
        ("Aufzug 630 kg", "elevator"),
        ("ELEVATOR", "elevator"),
        ("Treppe-EG", "stairs"),
        ("STRAIGHT_RUN_STAIR", "stairs"),
        ("Wendeltreppe", "stairs"),
        ("Kuehlschrank", "refrigerator"),  # before "schrank"
        # words that contain a rule's word but are something else
        ("Theater Seat", "chair"),
        ("Treppenhocker", "chair"),
        ("Lift table", "table"),
        ("Rollcontainer", "cabinet"),
        ("Waste container", None),
        ("Spindel", None),
        ("Monitoring panel", None),
        ("Kubus-Einrichtung-2", None),
        ("Parking", None),
    ],
)
def test_rules(vocabulary: Vocabulary, text: str, label: str | None) -> None:
    assert vocabulary.match_text(text) == label


def test_name_wins_over_a_misleading_type_name(vocabulary: Vocabulary) -> None:
    # AC11-FZK-Haus: the double bed's furniture type is called "Bad" (German: bathroom).
    [label] = label_elements([element(name="Doppelbett", type_name="Bad")], vocabulary)
    assert (label.label, label.source) == ("bed", LabelSource.RULE)


def test_unnamed_elements_take_the_label_of_their_type_siblings(vocabulary: Vocabulary) -> None:
    kubus = "Kubus-Einrichtung-2"
    elements = [element(name="Stuhl", type_name=kubus)] * 3 + [element(type_name=kubus)]
    labels = label_elements(elements, vocabulary)
    assert labels[-1].label == "chair"
    assert labels[-1].source is LabelSource.TYPE_SIBLINGS


def test_fallbacks_embedding_then_ifc_class(vocabulary: Vocabulary) -> None:
    elements = [element(name="Recliner"), element("IfcWindow"), element("IfcFlowTerminal", name="xq-17")]
    labels = label_elements(elements, vocabulary, MiniLMTextEmbedder(), min_similarity=0.45)
    assert (labels[0].label, labels[0].source) == ("chair", LabelSource.EMBEDDING)
    assert (labels[1].label, labels[1].source) == ("window", LabelSource.IFC_CLASS)
    assert (labels[2].label, labels[2].source) == ("fixture", LabelSource.IFC_CLASS)
    assert labels[0].raw_text == "Recliner"


def test_a_class_that_names_the_element_outranks_the_embedding_guess(vocabulary: Vocabulary) -> None:
    # A radiator named by a product code alone was labelled "piano" by the nearest text embedding.
    elements = [
        element("IfcFlowTerminal", name="Kermi Therm-X2 Profil-K 22", type_class="IfcSpaceHeaterType"),
        element("IfcStair", name="Stair:Residential 200mm"),
        element("IfcFlowTerminal", name="Kermi Therm-X2 Profil-K 22"),
    ]
    labels = label_elements(elements, vocabulary, MiniLMTextEmbedder(), min_similarity=0.0)
    assert (labels[0].label, labels[0].source) == ("radiator", LabelSource.IFC_CLASS)
    assert labels[1].label == "stairs"
    assert labels[2].source is LabelSource.EMBEDDING  # a plain flow terminal's class says nothing specific


def test_vocabulary_labels_are_unique_and_embeddable(vocabulary: Vocabulary) -> None:
    labels = vocabulary.labels
    assert len(labels) == len(set(labels)) and "chair" in labels
    vectors = MiniLMTextEmbedder().encode(labels)
    assert vectors.shape == (len(labels), 384)
    assert np.allclose(np.linalg.norm(vectors, axis=1), 1.0, atol=1e-5)
