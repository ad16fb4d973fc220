"""Exports of a release for other tools: the glTF blendshape rig and the offline interactive viewer."""
