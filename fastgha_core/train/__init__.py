"""Training and evaluation: the paper's losses (``losses``), VGG16 / LPIPS (``vgg``, ``lpips``),
image and face metrics (``metrics``, ``faces``), the DDP-capable trainer (``trainer``) and the
held-out evaluation (``evaluate``). Import the submodules directly; nothing heavy loads here."""
