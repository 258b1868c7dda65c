"""A display-only front end through meshcat: the deformed mesh streamed every frame."""

from __future__ import annotations

import sys

from pienerf.viewer.loop import DemoApp

__all__ = ["MeshcatViewer"]


class MeshcatViewer:
    """Display-only viewer through meshcat: the deformed mesh streamed every frame."""

    def __init__(self, zmq_url: str | None = None):
        import meshcat  # deferred: the optional meshcat viewer

        self.vis = meshcat.Visualizer(zmq_url=zmq_url)
        self.url = self.vis.url()

    def attach(self, app: DemoApp) -> None:
        self.app = app

    def update(self, app: DemoApp) -> None:
        import meshcat.geometry as g  # deferred: the optional meshcat viewer

        sim = app.simulation
        vertices = sim.deformed_mesh_vertices().numpy()
        colors = sim.mesh_colors.numpy()
        geometry = g.TriangularMeshGeometry(vertices, sim.mesh_faces.numpy(), color=colors)
        self.vis["body"].set_object(geometry, g.MeshLambertMaterial(vertexColors=True))

    def report(self, message: str) -> None:
        print(message, file=sys.stderr)

    def close(self) -> None:
        self.vis.delete()
