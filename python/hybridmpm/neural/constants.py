"""Constants shared by the torch model, the exporter and the onnxruntime runtime (no torch import)."""

#: Version of the feature construction inside exported models (bump on any change).
FEATURE_VERSION = 1
#: Largest wall reach (wall-distance features saturate at ``wall_reach·R``; 1 is GNS's clip).
WALL_REACH_MAX = 16.0
#: Particle-type vocabulary of the embedding (GNS: 9 types).
NUM_TYPES = 9
#: ONNX metadata property holding the model's JSON metadata.
METADATA_KEY = "hybridmpm"
#: Metadata key of a GNS's grid branch (a JSON object in the ``hybridmpm`` metadata; hybridmpm.neural.grid_branch).
BRANCH_KEY = "grid_branch"
#: The input of a GNS graph with a grid branch that takes the gathered context (hybridmpm.neural.grid_branch).
CONTEXT_INPUT = "grid_context"
#: Layout of the compiled GNS inference graph (:mod:`hybridmpm.train.gns.onnx_graph`), stored as ``graph``
#: in the model metadata; the runtime refuses a compiled graph of any other layout (re-export it).
GRAPH_LAYOUT = "compiled-3"
#: Inputs of the GNS inference graph, in order (graphs of torch's exporter, which have no ``graph`` in
#: their metadata, take the first four; compiled graphs the first eight, those of a GNS with a grid
#: branch all nine).
INPUT_NAMES = ("positions", "particle_type", "senders", "receivers", "displacement", "distance", "in_edges", "in_degree", CONTEXT_INPUT)
#: Outputs of the GNS inference graph, in order.
OUTPUT_NAMES = ("acceleration", "next_position")

__all__ = ["BRANCH_KEY", "CONTEXT_INPUT", "FEATURE_VERSION", "GRAPH_LAYOUT", "INPUT_NAMES", "METADATA_KEY", "NUM_TYPES", "OUTPUT_NAMES", "WALL_REACH_MAX"]
