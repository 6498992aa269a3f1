"""The decentralized mode: FLOCC-SLAM (``papers/FLOCC-SLAM.txt``).

Each robot brings a metric odometry and its images; robots in communication range find
inter-robot loop closures with the prior and an elected robot solves a scale-aware
multi-robot pose graph in GTSAM.

* :mod:`como3r.config_decentralized` -- its configuration,
  :class:`~como3r.config_decentralized.DecentralizedConfig`;
* :mod:`.odometry_sim` -- VIO/LIO-like ``odometry.txt`` for synthetic robots
  (:func:`~.odometry_sim.add_odometry`);
* :mod:`.keyframes` -- keyframes by travelled distance;
* :mod:`.place_recognition` -- global place descriptors and loop candidates (F-Sec. III-A);
* :mod:`.registration` -- two-stage encode/decode registration (F-Sec. III-B);
* :mod:`.confidence` -- the correspondence-ratio confidence (F-Eq. 1-2);
* :mod:`.pose_graph` -- base, independent, smoothed and shared-scale graphs, LM and GNC
  (F-Sec. III-C), on :mod:`.pose_graph_problem` from :mod:`.initial_estimate`;
  :mod:`.consistency` -- pairwise consistency of the loops;
* :mod:`.messages`, :mod:`.robot`, :mod:`.protocol`, :mod:`.schedule`, :mod:`.routing` --
  robots, rendezvous, election, routing;
* :mod:`.runner` -- :func:`~.runner.run_decentralized`, the mode end to end, writing
  :mod:`.outputs`; :mod:`.robot_node` and :mod:`.zenoh_robot` -- ``como3r robot``, one robot
  per process over Zenoh.
"""
