// Core template instantiations (online path) for float; see inst_online.inc.
#define MAGVEC_INST_SCALAR float
#include "inst_online.inc"
