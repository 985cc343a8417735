/* The matching configurations the evaluation suite compares (ablation rows): initial map
 * x refinement basis, named as in the suite's JSON and docs/RESULTS.md. */
#ifndef EVAL_CONFIGS_H
#define EVAL_CONFIGS_H

#include "sm_match.h"

typedef struct eval_config {
  const char *name;
  int init, basis; /* enum sm_match_init, enum sm_match_basis */
} eval_config;

static const eval_config CONFIGS[] __attribute__((unused)) = {
    {"nn+lb", SM_INIT_NN, SM_MATCH_LB},
    {"nn+elastic", SM_INIT_NN, SM_MATCH_ELASTIC},
    {"sinkhorn+lb", SM_INIT_SINKHORN, SM_MATCH_LB},
    {"sinkhorn+elastic", SM_INIT_SINKHORN, SM_MATCH_ELASTIC},
    {"sinkhorn+hybrid", SM_INIT_SINKHORN, SM_MATCH_HYBRID},
};
#define N_CONFIGS ((int)(sizeof CONFIGS / sizeof CONFIGS[0]))

#endif
