"""VL-Map in Foxglove: the live WebSocket server (`vlmap foxglove`, `app.foxglove.live`) and MCAP recordings
(`GET /v1/sessions/{id}/recording.mcap`, `vlmap record`, `app.foxglove.recording`), both from a session's
recording frames (`app.sessions.recording`) through one conversion (`app.foxglove.messages`), so that both
have the same topics and schemas.

Topics, per session `<s>` (its id), in the scene graph's frame (`frame_id`, "map" by default):

    /vlmap/<s>/scene_graph  foxglove.SceneUpdate  object boxes with their labels, region boxes; at each change
    /vlmap/<s>/belief       foxglove.PointCloud   the 100 most probable voxels: x, y, z, probability, and
                                                  red/green/blue/alpha by probability; one per version
    /vlmap/<s>/estimate     foxglove.SceneUpdate  the MAP voxel (a cube) and the posterior mean with its
                                                  covariance (an ellipsoid at 2 sigma); one per version
    /vlmap/<s>/summary      JSON (vlmap.BeliefSummary)  the version's posterior summary as `GET .../belief`
                                                  has it (MAP, top voxels, mean, covariance, entropy, mass
                                                  per object and region); one per version
    /vlmap/<s>/mixture      foxglove.SceneUpdate  the last fused utterance's mixture: one ellipsoid per
                                                  Gaussian at its 2-sigma surface, labelled with its
                                                  hypothesis and weight; uniform boxes as wireframes
    /vlmap/<s>/utterances   foxglove.Log          each utterance, fused or not, with its best hypotheses
"""
