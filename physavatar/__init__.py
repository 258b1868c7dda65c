"""PhysAvatar: garment physics and appearance from multi-view video, and animation under new motions.

Layers, each importing only those before it:

- :mod:`~physavatar.shapes`, :mod:`~physavatar.result_files`: test meshes; whole-or-nothing result files;
- :mod:`~physavatar.body` (the skinned mannequin and its motions), :mod:`~physavatar.cloth` (the garment solver);
- :mod:`~physavatar.intersections`: a captured garment moved out of the body and apart from itself, so that the
  simulator can start from it;
- :mod:`~physavatar.garment`, :mod:`~physavatar.drive`, :mod:`~physavatar.simulate`: a garment on the body, what
  moves it each step, and the simulation of a motion (the forward problem); :mod:`~physavatar.session`: the same,
  interactive, behind the viewer's verbs (playback, drag and pins, fabric, contact);
- :mod:`~physavatar.capture`: cameras, renderer, capture files, and a researcher's capture folder (whose garment
  mesh it reads as :mod:`~physavatar.garment` does);
- :mod:`~physavatar.fit`: tracking, physics and appearance estimation from a capture, and their scores;
- :mod:`~physavatar.pipeline`: the stages end to end and their report.
"""
