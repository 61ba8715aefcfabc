"""Independent float64 NumPy reference for the BRDF terms, transcribed from docs/math.md §1, §2.

Written straight from the textbook forms (not from jaxpbr, which is deliberately *not* imported
here): the GGX NDF as `alpha^2 / (pi ((NoH^2)(alpha^2 - 1) + 1)^2)`, Smith through Lambda, the
visibility as `G2 / (4 NoV NoL)`, the glTF 2.0 Appendix B material exactly as its text writes it,
and a line-by-line transcription of the LearnOpenGL `pbr.fs` per-light code.

Conventions (docs/math.md §0): `n, v, l` unit vectors pointing away from the surface, `r` perceptual
roughness, `alpha = r^2`. Dot products are arrays of shape (...); colours (..., 3). All arithmetic
is float64 (inputs are converted with `np.asarray(x, np.float64)`).
"""

from __future__ import annotations

import numpy as np

PI = np.pi
F0_DIELECTRIC = 0.04  # ((1.5 - 1)/(1.5 + 1))^2, glTF App. B


def _f(x):
    return np.asarray(x, dtype=np.float64)


def dot(a, b):
    """Dot product over the last axis: (..., 3), (..., 3) -> (...)."""
    return np.sum(_f(a) * _f(b), axis=-1)


def normalize(x):
    """x / |x| over the last axis (no safety: the reference is only used on ordinary inputs)."""
    x = _f(x)
    return x / np.linalg.norm(x, axis=-1, keepdims=True)


def chi_plus(x):
    """Heaviside chi+(x): 1 for x > 0, else 0."""
    return (_f(x) > 0).astype(np.float64)


# --------------------------------------------------------------------------------------------
# §1.1 GGX NDF
# --------------------------------------------------------------------------------------------


def d_ggx(n_dot_h, alpha):
    """D(h) = alpha^2 / (pi ((n.h)^2 (alpha^2 - 1) + 1)^2) chi+(n.h)   (textbook form)."""
    nh = _f(n_dot_h)
    alpha = _f(alpha)
    a2 = alpha**2
    den = PI * (nh**2 * (a2 - 1.0) + 1.0) ** 2
    return a2 / den * chi_plus(nh)


# --------------------------------------------------------------------------------------------
# §1.2 Smith masking-shadowing (GGX)
# --------------------------------------------------------------------------------------------


def smith_lambda(mu, alpha):
    """Lambda(mu) = (-1 + sqrt(1 + alpha^2 tan^2 theta)) / 2, tan^2 = (1 - mu^2)/mu^2, mu > 0."""
    mu = _f(mu)
    alpha = _f(alpha)
    tan2 = (1.0 - mu**2) / mu**2
    return 0.5 * (-1.0 + np.sqrt(1.0 + alpha**2 * tan2))


def smith_g1(mu, alpha):
    """G1 = 1 / (1 + Lambda)."""
    return 1.0 / (1.0 + smith_lambda(mu, alpha))


def smith_g2_separable(n_dot_v, n_dot_l, alpha):
    """Uncorrelated Smith G2 = G1(NoV) G1(NoL)."""
    return smith_g1(n_dot_v, alpha) * smith_g1(n_dot_l, alpha)


def smith_g2_correlated(n_dot_v, n_dot_l, alpha):
    """Height-correlated Smith (Heitz 2014) G2 = 1 / (1 + Lambda(v) + Lambda(l)) (chi+ = 1 here)."""
    return 1.0 / (1.0 + smith_lambda(n_dot_v, alpha) + smith_lambda(n_dot_l, alpha))


def v_smith_correlated(n_dot_v, n_dot_l, alpha):
    """V = G2_correlated / (4 NoV NoL)."""
    nv, nl = _f(n_dot_v), _f(n_dot_l)
    return smith_g2_correlated(nv, nl, alpha) / (4.0 * nv * nl)


def v_smith_separable(n_dot_v, n_dot_l, alpha):
    """V = G1(NoV) G1(NoL) / (4 NoV NoL)."""
    nv, nl = _f(n_dot_v), _f(n_dot_l)
    return smith_g2_separable(nv, nl, alpha) / (4.0 * nv * nl)


# --------------------------------------------------------------------------------------------
# §1.3 Schlick-GGX
# --------------------------------------------------------------------------------------------


def k_direct(r):
    """k = (r + 1)^2 / 8 for analytic lights (Karis 2013)."""
    return (_f(r) + 1.0) ** 2 / 8.0


def k_ibl(r):
    """k = alpha / 2 with alpha = r^2 for IBL (Karis 2013)."""
    alpha = _f(r) ** 2
    return alpha / 2.0


def g1_schlick_ggx(mu, k):
    """G1_schlick(mu) = mu / (mu (1 - k) + k)."""
    mu, k = _f(mu), _f(k)
    return mu / (mu * (1.0 - k) + k)


def v_schlick_ggx(n_dot_v, n_dot_l, k):
    """V = G1_schlick(NoV) G1_schlick(NoL) / (4 NoV NoL)."""
    nv, nl = _f(n_dot_v), _f(n_dot_l)
    return g1_schlick_ggx(nv, k) * g1_schlick_ggx(nl, k) / (4.0 * nv * nl)


# --------------------------------------------------------------------------------------------
# §1.4 Fresnel
# --------------------------------------------------------------------------------------------


def schlick_weight(cos_theta):
    """(1 - cos)^5."""
    return (1.0 - _f(cos_theta)) ** 5


def fresnel_schlick(cos_theta, f0, f90=1.0):
    """F = F0 + (F90 - F0)(1 - cos)^5; broadcasting is the caller's business."""
    f0 = _f(f0)
    return f0 + (_f(f90) - f0) * schlick_weight(cos_theta)


def fresnel_schlick_roughness(n_dot_v, f0, r):
    """F_r = F0 + (max(1 - r, F0) - F0)(1 - NoV)^5; n_dot_v, r (...), f0 (..., 3)."""
    f0 = _f(f0)
    w = schlick_weight(n_dot_v)[..., None]
    return f0 + (np.maximum(1.0 - _f(r)[..., None], f0) - f0) * w


def f0_from_ior(ior):
    """F0 = ((ior - 1)/(ior + 1))^2."""
    ior = _f(ior)
    return ((ior - 1.0) / (ior + 1.0)) ** 2


def fresnel_avg(f0):
    """F_avg = 2 int_0^1 F(mu) mu dmu = (1 + 20 F0) / 21 (Schlick, F90 = 1)."""
    return (1.0 + 20.0 * _f(f0)) / 21.0


# --------------------------------------------------------------------------------------------
# §2 Diffuse
# --------------------------------------------------------------------------------------------


def lambert(c_diff):
    """f_d = c_diff / pi."""
    return _f(c_diff) / PI


def burley(c_diff, r, n_dot_v, n_dot_l, l_dot_h):
    """Disney 2012 diffuse with perceptual r: F_D90 = 0.5 + 2 r cos^2(theta_d),
    f = c/pi (1 + (F_D90 - 1)(1 - NoL)^5)(1 + (F_D90 - 1)(1 - NoV)^5). c_diff (..., 3)."""
    fd90 = 0.5 + 2.0 * _f(r) * _f(l_dot_h) ** 2
    light = 1.0 + (fd90 - 1.0) * (1.0 - _f(n_dot_l)) ** 5
    view = 1.0 + (fd90 - 1.0) * (1.0 - _f(n_dot_v)) ** 5
    return _f(c_diff) / PI * (light * view)[..., None]


def blinn_phong(n_dot_h, shininess, normalized=False):
    """max(NoH, 0)^s, optionally times (s + 8)/(8 pi)."""
    s = _f(shininess)
    lobe = np.maximum(_f(n_dot_h), 0.0) ** s
    if normalized:
        lobe = lobe * (s + 8.0) / (8.0 * PI)
    return lobe


# --------------------------------------------------------------------------------------------
# glTF 2.0 Appendix B (exact text)
# --------------------------------------------------------------------------------------------


def mix(x, y, a):
    """GLSL mix: x (1 - a) + y a."""
    return _f(x) * (1.0 - _f(a)) + _f(y) * _f(a)


def fresnel_mix(v_dot_h, base, layer, f0=F0_DIELECTRIC):
    """glTF `fresnel_mix(ior=1.5, base, layer)`: fr = f0 + (1 - f0)(1 - |VoH|)^5; mix(base, layer, fr).

    base (..., 3) a colour (the diffuse BRDF); layer (...) a per-sample scalar (the specular BRDF).
    """
    fr = f0 + (1.0 - f0) * (1.0 - np.abs(_f(v_dot_h))) ** 5
    return mix(_f(base), _f(layer)[..., None], fr[..., None])


def conductor_fresnel(v_dot_h, f0, bsdf):
    """glTF `conductor_fresnel(f0, bsdf)` = bsdf (f0 + (1 - f0)(1 - |VoH|)^5).

    f0 (..., 3) a colour; bsdf (...) a per-sample scalar (the specular BRDF).
    """
    f0 = _f(f0)
    w = ((1.0 - np.abs(_f(v_dot_h))) ** 5)[..., None]
    return _f(bsdf)[..., None] * (f0 + (1.0 - f0) * w)


def gltf_material(n, v, l, base_color, metallic, roughness, smith="correlated", diffuse="lambert"):
    """glTF 2.0 App. B metallic-roughness BRDF, (..., 3), on front-facing configurations.

        specular_brdf   = D(alpha) G(alpha) / (4 |V.N| |L.N|)   (D: chi+(N.H); G: chi+(H.L) chi+(H.V))
        diffuse_brdf    = (1/pi) baseColor                     (or Burley with perceptual r)
        metal_brdf      = conductor_fresnel(f0 = baseColor, bsdf = specular_brdf)
        dielectric_brdf = fresnel_mix(ior = 1.5, base = diffuse_brdf, layer = specular_brdf)
        material        = mix(dielectric_brdf, metal_brdf, metallic)
    """
    n, v, l = normalize(n), normalize(v), normalize(l)
    h = normalize(v + l)
    nv, nl, nh = dot(n, v), dot(n, l), dot(n, h)
    vh, lh = dot(v, h), dot(l, h)
    r = _f(roughness)
    alpha = r**2
    D = d_ggx(nh, alpha)
    if smith == "correlated":
        G = smith_g2_correlated(np.abs(nv), np.abs(nl), alpha)
    elif smith == "separable":
        G = smith_g2_separable(np.abs(nv), np.abs(nl), alpha)
    else:
        raise ValueError(smith)
    G = G * chi_plus(lh) * chi_plus(vh)
    specular_brdf = D * G / (4.0 * np.abs(nv) * np.abs(nl))
    if diffuse == "lambert":
        diffuse_brdf = lambert(base_color)
    elif diffuse == "burley":
        diffuse_brdf = burley(base_color, r, nv, nl, lh)
    else:
        raise ValueError(diffuse)
    metal_brdf = conductor_fresnel(vh, base_color, specular_brdf)
    dielectric_brdf = fresnel_mix(vh, diffuse_brdf, specular_brdf)
    return mix(dielectric_brdf, metal_brdf, _f(metallic)[..., None])


# --------------------------------------------------------------------------------------------
# LearnOpenGL pbr.fs (per-light code path), transcribed line by line
# --------------------------------------------------------------------------------------------


def _clamp01(x):
    return np.clip(x, 0.0, 1.0)


def lo_distribution_ggx(N, H, roughness):
    """float a = roughness*roughness; a2 = a*a; NdotH = max(dot(N, H), 0); NdotH2 = NdotH*NdotH;
    denom = (NdotH2 * (a2 - 1) + 1); denom = PI * denom * denom; return a2 / denom."""
    a = roughness * roughness
    a2 = a * a
    NdotH = np.maximum(dot(N, H), 0.0)
    NdotH2 = NdotH * NdotH
    denom = NdotH2 * (a2 - 1.0) + 1.0
    denom = PI * denom * denom
    return a2 / denom


def lo_geometry_schlick_ggx(NdotV, roughness):
    """float r = roughness + 1; k = r*r / 8; return NdotV / (NdotV * (1 - k) + k)."""
    r = roughness + 1.0
    k = (r * r) / 8.0
    return NdotV / (NdotV * (1.0 - k) + k)


def lo_geometry_smith(N, V, L, roughness):
    """NdotV = max(dot(N,V),0); NdotL = max(dot(N,L),0); ggx2 = SchlickGGX(NdotV); ggx1 = ...(NdotL)."""
    NdotV = np.maximum(dot(N, V), 0.0)
    NdotL = np.maximum(dot(N, L), 0.0)
    ggx2 = lo_geometry_schlick_ggx(NdotV, roughness)
    ggx1 = lo_geometry_schlick_ggx(NdotL, roughness)
    return ggx1 * ggx2


def lo_fresnel_schlick(cosTheta, F0):
    """F0 + (1 - F0) * pow(clamp(1 - cosTheta, 0, 1), 5)."""
    return F0 + (1.0 - F0) * np.power(_clamp01(1.0 - cosTheta), 5.0)[..., None]


def learnopengl_pbr_fs(N, V, L, albedo, metallic, roughness, epsilon=1e-4):
    """The BRDF factor `(kD * albedo / PI + specular)` of one light in LearnOpenGL `pbr.fs`, (..., 3).

        vec3 F0 = vec3(0.04); F0 = mix(F0, albedo, metallic);
        vec3 H = normalize(V + L);
        float NDF = DistributionGGX(N, H, roughness);
        float G   = GeometrySmith(N, V, L, roughness);
        vec3 F    = fresnelSchlick(clamp(dot(H, V), 0.0, 1.0), F0);
        vec3 numerator    = NDF * G * F;
        float denominator = 4.0 * max(dot(N, V), 0.0) * max(dot(N, L), 0.0) + 0.0001;
        vec3 specular = numerator / denominator;
        vec3 kS = F; vec3 kD = vec3(1.0) - kS; kD *= 1.0 - metallic;
        ... (kD * albedo / PI + specular) ...
    `epsilon` is the shader's 0.0001 (0.0 gives the fudge-free D G F / (4 NoV NoL)).
    """
    N, V, L = normalize(N), normalize(V), normalize(L)
    albedo = _f(albedo)
    metallic = _f(metallic)
    roughness = _f(roughness)
    F0 = mix(np.full(3, 0.04), albedo, metallic[..., None])
    H = normalize(V + L)
    NDF = lo_distribution_ggx(N, H, roughness)
    G = lo_geometry_smith(N, V, L, roughness)
    F = lo_fresnel_schlick(_clamp01(dot(H, V)), F0)
    numerator = (NDF * G)[..., None] * F
    denominator = 4.0 * np.maximum(dot(N, V), 0.0) * np.maximum(dot(N, L), 0.0) + epsilon
    specular = numerator / denominator[..., None]
    kS = F
    kD = 1.0 - kS
    kD = kD * (1.0 - metallic)[..., None]
    return kD * albedo / PI + specular


# Cube faces (OpenGL major-axis table, written out by hand; shared by the cubemap/IBL tests).
def gl_inverse(face, sc, tc):
    """Point on the unit cube with face `face` and (sc, tc), solved by hand from GL_TABLE (|ma| = 1)."""
    one = np.ones_like(sc)
    cols = {
        0: (one, -tc, -sc),
        1: (-one, -tc, sc),
        2: (sc, one, tc),
        3: (sc, -one, -tc),
        4: (sc, -tc, one),
        5: (-sc, -tc, -one),
    }[face]
    return np.stack(cols, -1)


def cube_geometry(S):
    """Texel centres (6,S,S,3) unit and corners (6,S,S,4,3) on the cube; [f, i, j] <-> s=(j+.5)/S, t=(i+.5)/S."""
    e = np.linspace(-1.0, 1.0, S + 1)
    c = 0.5 * (e[:-1] + e[1:])
    cen, cor = [], []
    for f in range(6):
        tc, sc = np.meshgrid(c, c, indexing="ij")
        d = gl_inverse(f, sc, tc)
        cen.append(d / np.linalg.norm(d, axis=-1, keepdims=True))
        t0, s0 = np.meshgrid(e[:-1], e[:-1], indexing="ij")
        t1, s1 = np.meshgrid(e[1:], e[1:], indexing="ij")
        cor.append(
            np.stack([gl_inverse(f, s0, t0), gl_inverse(f, s1, t0), gl_inverse(f, s1, t1), gl_inverse(f, s0, t1)], -2)
        )
    return np.stack(cen), np.stack(cor)


def solid_angles(S):
    """Texel solid angles (6,S,S) by the corner formula: the solid angle of [0,x]x[0,y] on the plane z=1
    is atan2(xy, sqrt(1+x^2+y^2)) (same for every face)."""
    e = np.linspace(-1.0, 1.0, S + 1)
    A = lambda x, y: np.arctan2(x * y, np.sqrt(1.0 + x * x + y * y))  # noqa: E731
    x0, x1, y0, y1 = e[None, :-1], e[None, 1:], e[:-1, None], e[1:, None]
    return np.broadcast_to(A(x1, y1) - A(x0, y1) - A(x1, y0) + A(x0, y0), (6, S, S))


def polygon_moment(V):
    """Exact first moment  int w dw  over the spherical (central) projection of a planar convex polygon
    V (..., k, 3) (Lambert / Arvo: 1/2 sum_edges theta_e * unit(v_e x v_e+1)), oriented to point at the
    polygon; repeated vertices are allowed. For texels: polygon_moment(cube_geometry(S)[1])."""
    U = V / np.linalg.norm(V, axis=-1, keepdims=True)
    W = np.roll(U, -1, axis=-2)
    cr = np.cross(U, W)
    nrm = np.linalg.norm(cr, axis=-1)
    th = np.arctan2(nrm, np.sum(U * W, -1))
    m = 0.5 * np.sum(th[..., None] * cr / np.where(nrm > 0, nrm, 1.0)[..., None], -2)
    return m * np.sign(np.sum(m * V.mean(-2), -1))[..., None]


def schlick_lambert_average(mu, k=256):
    """C(mu) = (1/pi) integral (1 - v.h)^5 (n.l)+ dl over the hemisphere of l, by Gauss-Legendre in
    (cos theta_l, phi): the Schlick-weighted cosine mean of a Lambert lobe seen at n.v = mu."""
    x, w = np.polynomial.legendre.leggauss(k)
    ct, wct = 0.5 * (x + 1), 0.5 * w
    ph, wph = np.pi * (x + 1), np.pi * w
    C, P = np.meshgrid(ct, ph, indexing="ij")
    S = np.sqrt(1 - C * C)
    l = np.stack([S * np.cos(P), S * np.sin(P), C], -1)  # noqa: E741
    v = np.array([np.sqrt(1 - mu * mu), 0.0, mu])
    voh = np.sqrt(np.maximum((1 + l @ v) / 2, 0))
    return float(((1 - voh) ** 5 * C / np.pi * np.outer(wct, wph)).sum())
