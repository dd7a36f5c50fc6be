"""The tissue domain in the reference configuration: outline, edges, normals, inside tests,
distances and boundary segments.

Every layer asks the domain these questions instead of comparing coordinates with 0, W
and H itself, so another shape (a polygon, holes) is another domain class with the same
methods, not a change to the numerics. Points are (..., 2) arrays in mm.

Modules, each importing only those before it:

- segments: straight segments (on_segment, segments_cross, segments_touch, the distance to one);
- edge_grid: EdgeGrid, edges binned on a grid so a query meets only the edges near it;
- polygons: polygons as vertex arrays (signed_area, turns, circle_polygon, polygon_problem,
  cut_outline);
- bounding_box: BoundingBox, the base of both domains, and the input tolerances;
- polygon_domain: PolygonDomain, and circle_crossings (which both domains answer with);
- rectangle: Rectangle and its EDGE_NAMES, circle_center_at_entry;
- boundary: boundary queries of any domain (boundary_edges, nearest_on_edges,
  nearest_boundary_point, snap_to_boundary, smooth_vertex).
"""
