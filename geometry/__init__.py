"""Geometry for cpdetect: cameras, transforms, fusion, clustering, ray casting, adjustment,
registration and CRS handling. Depends on numpy/scipy/open3d/pyproj only: never imports cpdetect,
learned or torch."""
