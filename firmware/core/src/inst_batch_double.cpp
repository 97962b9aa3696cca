// Core template instantiations (batch path) for double; see inst_batch.inc.
#define MAGVEC_INST_SCALAR double
#include "inst_batch.inc"
