"""sss2bathy: sidescan sonar -> surface normals -> neural bathymetry (Xie, Bore, Folkesson 2022)."""

__version__ = "0.1.0"
