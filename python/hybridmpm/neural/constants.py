"""Constants shared by the torch model, the exporter and the onnxruntime runtime (no torch import)."""

from hybridmpm.conventions import GNS_KINEMATIC as KINEMATIC

#: Version of the feature construction inside exported models (bump on any change).
FEATURE_VERSION = 1
#: Particle-type vocabulary of the embedding (GNS: 9 types).
NUM_TYPES = 9
#: ONNX metadata property holding the model's JSON metadata.
METADATA_KEY = "hybridmpm"

__all__ = ["FEATURE_VERSION", "KINEMATIC", "METADATA_KEY", "NUM_TYPES"]
