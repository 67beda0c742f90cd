"""Write ``scenes/room.xml``: a room-like example scene for ``mi-gs optimize`` that declares its own cameras.

A closed 4 x 2.6 x 4 room (Y up) lit by a ceiling area light, with a checkered rug (textured diffuse), a copper
sphere (rough conductor), a green glossy plastic box (rough plastic), a checkered cube and a cylinder. Cameras cannot
sit outside a room, so the scene declares ``N_SENSORS`` sensors inside it (two rings at different heights, each
looking across the room at a point near its centre); ``mi-gs optimize`` uses declared sensors as the views, holding
out every 8th. Nothing to download: every texture is Mitsuba's procedural checkerboard.

    python scenes/make_room.py          # rewrites scenes/room.xml (deterministic)
"""

from __future__ import annotations

import math
from pathlib import Path

N_SENSORS = 32
WIDTH, HEIGHT, FOV = 160, 120, 70.0

HEADER = """<!-- Room-like example scene for `mi-gs optimize` (written by scenes/make_room.py; edit that script, not this file).

     mi-gs optimize scenes/room.xml -o out/room      the {n} declared sensors are the views (every 8th held out)
     mi-gs render scenes/room.xml -o room.exr        path-trace the first sensor

     A closed room lit by a ceiling area light: checkered rug (textured diffuse), copper sphere (rough conductor),
     green glossy box (rough plastic), checkered cube, white cylinder. Y up, metres. -->
<scene version="3.0.0">
    <default name="spp" value="256"/>

    <integrator type="path">
        <integer name="max_depth" value="5"/>
    </integrator>
"""

BODY = """
    <bsdf type="diffuse" id="wall">
        <rgb name="reflectance" value="0.75, 0.72, 0.66"/>
    </bsdf>
    <bsdf type="diffuse" id="accent_wall">
        <rgb name="reflectance" value="0.25, 0.4, 0.6"/>
    </bsdf>
    <bsdf type="diffuse" id="wood_floor">
        <rgb name="reflectance" value="0.45, 0.3, 0.18"/>
    </bsdf>
    <bsdf type="diffuse" id="rug_bsdf">
        <texture type="checkerboard" name="reflectance">
            <rgb name="color0" value="0.75, 0.7, 0.55"/>
            <rgb name="color1" value="0.55, 0.12, 0.1"/>
            <transform name="to_uv">
                <scale x="6" y="6"/>
            </transform>
        </texture>
    </bsdf>
    <bsdf type="roughconductor" id="copper">
        <string name="material" value="Cu"/>
        <string name="distribution" value="ggx"/>
        <float name="alpha" value="0.2"/>
    </bsdf>
    <bsdf type="roughplastic" id="green_plastic">
        <rgb name="diffuse_reflectance" value="0.08, 0.45, 0.12"/>
        <float name="alpha" value="0.1"/>
    </bsdf>
    <bsdf type="diffuse" id="checker_bsdf">
        <texture type="checkerboard" name="reflectance">
            <rgb name="color0" value="0.85, 0.8, 0.2"/>
            <rgb name="color1" value="0.1, 0.1, 0.12"/>
            <transform name="to_uv">
                <scale x="4" y="4"/>
            </transform>
        </texture>
    </bsdf>
    <bsdf type="diffuse" id="white">
        <rgb name="reflectance" value="0.8"/>
    </bsdf>

    <!-- the room: rectangles facing inwards (a rectangle spans [-1, 1]^2 in xy and faces +z) -->
    <shape type="rectangle" id="floor">
        <transform name="to_world"><scale x="2" y="2"/><rotate x="1" angle="-90"/></transform>
        <ref id="wood_floor"/>
    </shape>
    <shape type="rectangle" id="ceiling">
        <transform name="to_world"><scale x="2" y="2"/><rotate x="1" angle="90"/><translate y="2.6"/></transform>
        <ref id="wall"/>
    </shape>
    <shape type="rectangle" id="wall_back">
        <transform name="to_world"><scale x="2" y="1.3"/><translate y="1.3" z="-2"/></transform>
        <ref id="accent_wall"/>
    </shape>
    <shape type="rectangle" id="wall_front">
        <transform name="to_world"><scale x="2" y="1.3"/><rotate y="1" angle="180"/><translate y="1.3" z="2"/></transform>
        <ref id="wall"/>
    </shape>
    <shape type="rectangle" id="wall_left">
        <transform name="to_world"><scale x="2" y="1.3"/><rotate y="1" angle="90"/><translate x="-2" y="1.3"/></transform>
        <ref id="wall"/>
    </shape>
    <shape type="rectangle" id="wall_right">
        <transform name="to_world"><scale x="2" y="1.3"/><rotate y="1" angle="-90"/><translate x="2" y="1.3"/></transform>
        <ref id="wall"/>
    </shape>
    <shape type="rectangle" id="ceiling_light">
        <transform name="to_world"><scale x="0.6" y="0.6"/><rotate x="1" angle="90"/><translate y="2.59"/></transform>
        <emitter type="area">
            <rgb name="radiance" value="9, 8.6, 8"/>
        </emitter>
    </shape>

    <!-- furniture -->
    <shape type="rectangle" id="rug">
        <transform name="to_world"><scale x="1.1" y="0.8"/><rotate x="1" angle="-90"/><translate y="0.002"/></transform>
        <ref id="rug_bsdf"/>
    </shape>
    <shape type="sphere" id="copper_sphere">
        <point name="center" value="0.55, 0.35, 0.3"/>
        <float name="radius" value="0.35"/>
        <ref id="copper"/>
    </shape>
    <shape type="cube" id="green_box">
        <transform name="to_world"><scale x="0.3" y="0.25" z="0.3"/><rotate y="1" angle="20"/><translate x="-0.6" y="0.25" z="-0.3"/></transform>
        <ref id="green_plastic"/>
    </shape>
    <shape type="cube" id="checker_cube">
        <transform name="to_world"><scale value="0.2"/><rotate y="1" angle="-35"/><translate x="-0.7" y="0.7" z="-0.3"/></transform>
        <ref id="checker_bsdf"/>
    </shape>
    <shape type="cylinder" id="column">
        <point name="p0" value="1.3, 0, -1.3"/>
        <point name="p1" value="1.3, 1.6, -1.3"/>
        <float name="radius" value="0.15"/>
        <ref id="white"/>
    </shape>
</scene>
"""

SENSOR = """
    <sensor type="perspective" id="cam_{i:02d}">
        <float name="fov" value="{fov}"/>
        <transform name="to_world">
            <lookat origin="{ox:.4f}, {oy:.4f}, {oz:.4f}" target="{tx:.4f}, {ty:.4f}, {tz:.4f}" up="0, 1, 0"/>
        </transform>
        <sampler type="multijitter">
            <integer name="sample_count" value="$spp"/>
        </sampler>
        <film type="hdrfilm">
            <integer name="width" value="{w}"/>
            <integer name="height" value="{h}"/>
            <string name="pixel_format" value="rgba"/>
            <rfilter type="box"/>
        </film>
    </sensor>
"""


def sensors() -> str:
    out = []
    for i in range(N_SENSORS):
        ring = i % 2                        # alternate rings: low (1.0 m) and high (1.8 m)
        a = 2.0 * math.pi * i / N_SENSORS
        r = 1.55 if ring == 0 else 1.3
        o = (r * math.cos(a), 1.0 if ring == 0 else 1.8, r * math.sin(a))
        t = (0.35 * math.cos(a + 2.2), 0.4, 0.35 * math.sin(a + 2.2))   # across the room, near its centre
        out.append(SENSOR.format(i=i, fov=FOV, ox=o[0], oy=o[1], oz=o[2], tx=t[0], ty=t[1], tz=t[2],
                                 w=WIDTH, h=HEIGHT))
    return "".join(out)


def main() -> None:
    path = Path(__file__).with_name("room.xml")
    path.write_text(HEADER.format(n=N_SENSORS) + sensors() + BODY)
    print(path)


if __name__ == "__main__":
    main()
