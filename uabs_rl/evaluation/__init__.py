"""Policies measured on held-out traces: the evaluator, the greedy, oracle and
planner baselines, paired statistics and the plots."""
