"""A video's clip over time: py-feat's per-frame AUs and head pose (:mod:`.clip`), as a glTF morph-weight animation of
the release's blendshape rig (:mod:`.gltf_clip`)."""
