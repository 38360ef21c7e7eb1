"""Scene -> models, states and solvers: the only code that reads scene keys and turns them into typed options
(seeding, block entries, rock masses, checks made before anything is allocated)."""
