"""The embedded default dataset: a procedural, ray-cast synthetic LiDAR world.

Modules (one idea each): ``roads`` (centre-line geometry), ``ground`` (height /
class / reflectivity rasters), ``primitives`` (analytic shapes), ``objects``
(cars, people, trees... from primitives), ``layout`` (where things go),
``scene`` (generate_scene), ``trajectory`` (platform poses), ``raycast``
(numba ray caster), ``radiometry`` (detection and remission), ``render``
(one sweep -> Scan), ``sequence`` (seeds, scans along a route), ``export``
(dataset layouts), ``statistics`` (scan_statistics). Nothing is imported here
so that ``omnilidar --help`` stays fast.
"""
