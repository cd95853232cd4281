"""Adaptivity rules, each a :class:`~nepf_core.train.rules.callback.RuleCallback`: called at every
point of a run, it acts at the steps of its own cadence, sets the switches of the run state it
owns and returns :class:`~nepf_core.train.decisions.Decision` records; the coordinator
(:class:`nepf_core.train.adaptivity.Adaptivity`) calls them in order and logs the decisions.
Each reads the config's ``rules`` section (:class:`~nepf_core.train.rules.config.RuleConfig`).

* :mod:`.masks`: mask loss, background model and object region from the data, before training;
* :mod:`.occupancy`: the occupancy grid's visual-hull carving and refreshes (empty space);
* :mod:`.empty_rays`: rays that meet no occupied cell leave the batch;
* :mod:`.hessian`: the Hessian term only while the surface is rough;
* :mod:`.specular` (with :mod:`.lobe_evidence`): drop the GGX lobe when the learned radiance is
  view-independent, fade it out, bring it back when the evidence returns;
* :mod:`.plateau`: early stop at a held-out plateau, after a learning-rate cool-down.
"""
