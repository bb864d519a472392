"""The names the ``dualscale`` parser offers as choices, as plain tuples.

Building the parser must not import the modules that define these names: they load torch,
scipy, kornia or OpenImageIO, seconds of CPU before ``dualscale --help`` could answer (issue 15,
"an instant command line"; docs/ARCHITECTURE.md, "Start-up").  The modules stay the source
of truth: ``tests/test_cli_startup.py`` checks that each tuple here holds the same names as its
source (:data:`STAGES` and :data:`CAPTURE_PLANS` in the same order, which the help shows), so a
name added there and not here fails the tests.
"""

#: ``synth MATERIAL`` -- the keys of :data:`dualscale.sim.materials.MATERIALS`
MATERIALS = ("plain", "twill", "satin", "denim", "rib_knit", "leather", "sheer", "brick", "grass", "gravel")

#: ``fit --preset``, ``study lights --preset`` -- the keys of :data:`dualscale.fit.presets.PRESETS`
FIT_PRESETS = ("paper", "standard", "draft", "coarse-to-fine", "adam-fast", "standard-compiled")

#: ``fit --kernel`` -- :data:`dualscale.fit.presets.KERNELS`
FIT_KERNELS = ("fused", "eager", "compiled")

#: ``propagate train --preset`` -- the keys of :data:`dualscale.propagate.train.PRESETS`
PROPAGATE_PRESETS = ("paper", "balanced", "fast", "quick")

#: ``propagate train --schedule`` -- the keys of :data:`dualscale.propagate.schedule.SCHEDULES`
SCHEDULES = ("constant", "onecycle")

#: ``propagate train --perceptual`` -- the keys of :data:`dualscale.propagate.losses.PERCEPTUAL`
PERCEPTUAL = ("gram", "lpips_alex")

#: ``digitize --quality`` -- the keys of :data:`dualscale.pipeline.QUALITIES`
QUALITIES = ("draft", "standard", "paper")

#: ``digitize --until`` -- :data:`dualscale.pipeline.STAGES`
STAGES = ("calibrate", "fit", "flyouts", "propagate", "export", "report")

#: ``capture PLAN`` -- the keys of :data:`dualscale.capture.plan.PLANS`, in its order (the help lists them so)
CAPTURE_PLANS = ("micro", "mid", "white-sheet", "chart", "dot-grid", "polarization")
