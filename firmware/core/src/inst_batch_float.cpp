// Core template instantiations (batch path) for float; see inst_batch.inc.
#define MAGVEC_INST_SCALAR float
#include "inst_batch.inc"
