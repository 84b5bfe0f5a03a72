"""The interactive playground (``resireg-playground``): similarity maps of BB, ReSiReg Lite and
ReSiReg Full (and Full with a SAM 2 prior) side by side for an uploaded or example image and
text queries, with ReSiReg's parameters as sliders.

- :mod:`.examples`: the example images (real photographs shipped by scikit-image),
- :mod:`.core`: loading an encoder, the computation and the rendering (torch, no web code),
- :mod:`.app`: the Gradio page.

Importing this package loads nothing heavy; torch and Gradio load with :mod:`.core` and
:mod:`.app`.

Imports ``resireg`` and the config helpers. May be imported by the CLIs only
(``resireg-playground``).
"""
