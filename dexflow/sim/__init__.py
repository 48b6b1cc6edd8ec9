"""Physics engines: the scenes in which stage simulate tests grasps and stage replay plays
trajectories back.

- :mod:`dexflow.sim.world`: the interface every engine's grasp world implements;
- :mod:`dexflow.sim.mujoco_world`: MuJoCo (the default engine, and the replay's);
- :mod:`dexflow.sim.pybullet_world`: pybullet;
- :mod:`dexflow.sim.protocol`: what the engines' grasp tests share (push directions, the push
  step, perturbed trials);
- :mod:`dexflow.sim.scene_check`: ``dexflow hand check``'s build-and-step check of every scene.
"""
