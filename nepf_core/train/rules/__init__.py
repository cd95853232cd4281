"""Adaptivity rules: each reads the config's ``rules`` section (:class:`~nepf_core.train.rules.config.RuleConfig`) and
returns :class:`~nepf_core.train.decisions.Decision` objects; the coordinator
(:class:`nepf_core.train.adaptivity.Adaptivity`) applies them to the run state.

* :mod:`.masks`: mask loss and background model from the data, before training;
* :mod:`.occupancy`: the occupancy grid's visual-hull carving and refreshes (empty space);
* :mod:`.empty_rays`: rays that meet no occupied cell leave the batch;
* :mod:`.hessian`: the Hessian term only while the surface is rough;
* :mod:`.specular` (with :mod:`.lobe_evidence`): drop the GGX lobe when the learned radiance is
  view-independent, fade it out, bring it back when the evidence returns;
* :mod:`.plateau`: early stop at a held-out plateau, after a learning-rate cool-down.
"""
