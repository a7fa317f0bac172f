"""Import a subset of Mitsuba 3's scene XML (and Nori's dialect of it).

`load_mitsuba_xml(path, **defaults)` reads a scene file and its includes and
feeds `SceneBuilder`. Anything outside the subset below is a `SceneError`
whose one line names ``file:line`` and the element, for example
``cbox.xml:42: <bsdf type="plastic">: unsupported plugin``: nothing is
silently dropped, in the spirit of Mitsuba's "unreferenced property" errors.

==========  ================================================================
element     plugins and parameters understood
==========  ================================================================
scene       ``version``; ``<default name value>`` and ``$name`` (keyword
            arguments override defaults; an unused keyword is an error);
            ``<include filename>``; ``<path value>`` (a folder searched for
            relative file names); ``id`` on any object, ``<ref id>``
shape       obj, ply (filename, face_normals); rectangle; cube; sphere
            (center, radius; an icosphere of 20,480 triangles); disk (a fan
            of 256 triangles); cylinder (p0, p1, radius; 256 quads, open);
            all take to_world and flip_normals; shapegroup (shapes without
            emitters) and instance (to_world, one ``<ref>`` to a group),
            flattened into copies of the group's triangles
bsdf        diffuse (reflectance); twosided (one nested BSDF);
            conductor (material: "none" or one of Mitsuba's named
            conductors, as its RGB variants convert them (`metals`),
            specular_reflectance, eta, k); roughconductor (distribution,
            alpha or alpha_u = alpha_v, material, specular_reflectance,
            eta, k, sample_visible);
            dielectric (int_ior, ext_ior as numbers or Mitsuba's names;
            specular_reflectance equal to specular_transmittance) -> glass;
            roughdielectric (distribution ggx or beckmann, alpha, int_ior,
            ext_ior, specular_reflectance, specular_transmittance);
            plastic (int_ior, ext_ior, diffuse_reflectance,
            specular_reflectance, nonlinear); roughplastic (the same plus
            distribution and alpha); mask (opacity a number or a
            texture, one nested BSDF); blendbsdf (weight a number or a
            texture, two nested BSDFs); normalmap (a texture named
            normalmap) and bumpmap (one texture, scale) around a diffuse,
            rough conductor or rough plastic, with flip_invalid_normals and
            use_shadowing_function; principled and principledthin are
            refused. The colour of diffuse, conductors and dielectric, a
            mask's opacity and a blend's weight may be a texture (the last
            two: its luminance, clipped to [0, 1], as Mitsuba's eval_1)
texture     bitmap (filename: PNG, JPEG, BMP, ... or EXR; filter_type
            bilinear or nearest, wrap_mode repeat, mirror or clamp, raw,
            to_uv, format); checkerboard (color0, color1, to_uv);
            rawconstant (value, a float or a vector); mesh_attribute
            (name vertex_<p> or face_<p> of a PLY's <p>_0.. properties);
            nested in a BSDF under the parameter's name, or a ``<ref name
            id>``. Not on roughness (alpha)
emitter     area (radiance) in a shape or referenced by one; point (position
            or to_world, intensity); spot (to_world, intensity,
            cutoff_angle, beam_width); projector (to_world, fov or
            focal_length, fov_axis, a constant irradiance, scale: no
            texture); directional (direction or to_world,
            irradiance); constant (radiance); envmap (filename of a
            lat-long OpenEXR, scale, to_world a rotation); one of constant
            and envmap per scene
sensor      perspective, thinlens (fov or focal_length, fov_axis, to_world,
            near_clip, far_clip, focus_distance, aperture_radius);
            orthographic (to_world, whose scale sizes the view, near_clip,
            far_clip); film hdrfilm (width, height, pixel_format,
            component_format, sample_border, rfilter: gaussian (stddev;
            the default), box, tent (radius); sampled by the eye rays, not
            splatted); sampler (sample_count, seed)
integrator  path, volpath, volpathmis, ptracer, direct (max_depth, rr_depth,
            hide_emitters; `settings.scene_settings` renders max_depth M
            as our M - 1 and refuses hide_emitters true); moment (read through to the one integrator it
            wraps: our variance comes from our own estimator)
values      float, integer, boolean, string, point, vector, rgb, spectrum
            (constant or wavelength:value pairs); transform of translate,
            rotate, scale, matrix, lookat (each applied after the previous)
==========  ================================================================

What `Scene` cannot hold (integrator, max_depth, spp, far_clip, film filter,
pixel format) lands in ``scene.render_settings``, a dict with only the keys
the file sets.

Decisions:

* Colours are converted exactly as Mitsuba 3's RGB variants (`scalar_rgb`)
  do (`colour`): wavelength:value pairs are integrated against the CIE 1931
  curves (1,000 samples over 360-830 nm) and mapped to linear sRGB;
  reflectances are weighted by the D65 illuminant and clamped to [0, 1],
  emission is not weighted and only clamped at 0. A constant spectrum is
  grey for a reflectance but ``value * xyz_to_srgb(1, 1, 1)`` (slightly
  purple) for an emitter; RGB is taken as is.
* File names (meshes, includes) are looked up in the ``<path>`` folders,
  the latest first as Mitsuba's file resolver prepends them, then beside the
  file that names them, then beside the main file. A ``<path>`` folder is
  taken from the directory of the file that writes it. Unlike Mitsuba, the
  working directory is never searched: a scene loads the same from anywhere.
* Disks and cylinders become fine polygons (their area falls short by
  1e-4), spheres icospheres. A cylinder whose to_world shears it or scales
  its cross-section unevenly is refused: Mitsuba only warns, and renders a
  cylinder read off the transform rather than the transformed one.
* Textures read the hit's uv as Mitsuba does: an OBJ's or PLY's own
  coordinates (an OBJ's v turned to 1 - v, as Mitsuba's reader does), the
  built-in shapes' analytic (u, v) at their vertices, and (b1, b2) on a
  mesh without coordinates. 8-bit images are sRGB-decoded unless ``raw``.
* conductor and roughconductor take eta and k (one value, rgb or a
  constant spectrum) or a named material and both distributions, Beckmann
  being Mitsuba's default; a GGX roughconductor without eta and k is our
  "glossy", one without them a perfect mirror's Fresnel of 1.
* The front of a surface is its triangle winding (counter-clockwise), which
  emission and one-sided BSDFs use, and flip_normals reverses. Under a
  mirroring to_world Mitsuba keeps the front of rectangles and cubes outward
  (so we rewind them) while spheres and meshes turn.
* Shading normals are Mitsuba's: an OBJ or PLY interpolates its vertex
  normals (the file's, else Mitsuba's angle-weighted ones) unless
  face_normals is true; a sphere's and a cylinder's are the analytic
  shape's exactly; rectangles, cubes and disks are flat
  (`kernels.smooth`). Interpolated normals are turned to the winding's
  side (Mitsuba would orient by them; every shared scene has them
  agreeing with the winding).
* Nori's XML (no ``version``, ``<mesh>``, ``<camera>``, ``<color>``) is
  cheap to support and is: it is rewritten to the Mitsuba elements it means
  (camelCase names, albedo, mirror, a film for width/height, the top-level
  sampler) and read by the same code. Nori's image x axis runs opposite to
  Mitsuba's, so a Nori camera gets ``scale(-1, 1, 1)`` applied first; Nori's
  defaults (fov 30, 1280x720, grey BSDF on emitters) are kept.

Modules, in the order a file passes through them:

==========  ================================================================
xmltree     parse, with ``file:line`` on every element
nori        detect Nori's dialect and rewrite it to Mitsuba's elements
objects     the object tree: ``$name`` defaults, includes, ids, parameters
values      numbers, points, rgb, spectra and transforms (used by objects)
colour      spectra to linear sRGB as Mitsuba's RGB variants
params      typed parameter access; `finish` rejects an unread parameter
reader      `load_mitsuba_xml`: the steps above, then each scene-level
            object to its family: shapes, bsdfs, emitters, sensors (with
            film, sampler, integrator), sharing one `state.ReaderState`
==========  ================================================================
"""
from dosppm_core.scene.mitsuba.reader import load_mitsuba_xml

__all__ = ["load_mitsuba_xml"]
