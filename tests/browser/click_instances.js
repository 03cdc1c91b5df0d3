// Clicks instances in nerfstudio's viewer, in a real (headless) Chromium, as a person does:
// for each click, "View through image" puts the view at that training image's camera, the class is typed,
// "Click an instance" is pressed and the 3D view is clicked at the pixel of the image; then "Write masks".
//
// Usage: node click_instances.js PLAN.json
// PLAN: {"url", "chromium", "panel", "free_view", "clicks": [{"image", "class", "xy": [u, v]}], "camera": {"w", "h", "fx",
//        "fy", "cx", "cy"}, "confirm": "Write masks", "arm": "Click an instance", "screenshots": DIR,
//        "timeout_ms"}
// Prints one JSON line per step; exits 0 when every click was accepted and the confirm button pressed.
// A failing step leaves DIR/failure.png (and DIR/click-K.png after each click in any case).

'use strict';
const fs = require('fs');
const os = require('os');
const path = require('path');
const { chromium } = require('playwright-core');

const plan = JSON.parse(fs.readFileSync(process.argv[2], 'utf8'));
const timeout = plan.timeout_ms || 60000;

const started = Date.now();

function say(step, extra) {
  console.log(JSON.stringify({ step, s: (Date.now() - started) / 1000, ...extra }));
}

// The panel: the folder whose title is plan.panel.
function panel(page) {
  return page.locator(
    `xpath=//div[contains(@class, "mantine-Paper-root")][div[normalize-space(text()) = ${JSON.stringify(plan.panel)}]]`,
  ).first();
}

// The input on the row of a labelled element inside the panel.
function field(page, label) {
  return panel(page).locator(
    `xpath=.//label[normalize-space() = ${JSON.stringify(label)}]/ancestor::div[contains(@class, "mantine-Flex-root")][1]//input[not(@type = "hidden")]`,
  ).first();
}

function button(page, label) {
  return panel(page).getByRole('button', { name: label, exact: true });
}

async function waitForStatus(page, pattern) {
  const status = field(page, 'Status');
  const deadline = Date.now() + timeout;
  let value = '';
  while (Date.now() < deadline) {
    value = await status.inputValue();
    if (pattern.test(value)) return value;
    await page.waitForTimeout(100);
  }
  throw new Error(`status stayed "${value}", expected ${pattern}`);
}

function escapeRegExp(text) {
  return text.replace(/[.*+?^${}()|[\]\\]/g, '\\$&');
}

async function chooseImage(page, image) {
  const select = field(page, 'View through image');
  if ((await select.inputValue()) === image) {
    // choosing the entry shown sends nothing: leave it first
    await select.click();
    await page.getByRole('option', { name: plan.free_view, exact: true }).click();
  }
  await select.click();
  await page.getByRole('option', { name: image, exact: true }).click();
  // the server says so once it has sent the view's new camera (same connection, so it arrives after it)
  await waitForStatus(page, new RegExp(`^the view looks through ${escapeRegExp(image)}:`));
}

// The pixel of the 3D view that shows pixel (u, v) of the training image when the view looks through its
// camera: the view keeps the camera's vertical field of view over its own height, centred.
function viewPixel(canvas, xy, camera) {
  const scale = canvas.height / camera.h; // view pixels per image pixel (vertical field of view kept)
  const x = canvas.x + canvas.width / 2 + scale * (xy[0] + 0.5 - camera.cx) * (camera.fy / camera.fx);
  const y = canvas.y + canvas.height / 2 + scale * (xy[1] + 0.5 - camera.cy);
  return { x, y };
}

(async () => {
  const profile = fs.mkdtempSync(path.join(os.tmpdir(), 'splatreplace-chromium-'));
  const context = await chromium.launchPersistentContext(profile, {
    executablePath: plan.chromium,
    headless: true,
    viewport: { width: 1000, height: 480 }, // a 4:3 image fits beside the control panel
    args: [
      '--headless=new', '--enable-unsafe-swiftshader', '--use-angle=swiftshader', '--no-sandbox',
      '--disable-quic', '--no-first-run', '--disable-background-networking', '--disable-component-update',
      '--disable-sync',
    ],
  });
  const page = context.pages()[0] || (await context.newPage());
  page.setDefaultTimeout(timeout);
  let failed = false;
  try {
    await page.goto(plan.url);
    await page.getByText('Connected', { exact: true }).waitFor();
    await waitForStatus(page, /^(?!opens when)/); // clicking opens when the base stage has trained
    say('ready');
    // the 3D view (three.js draws it; a 2D canvas for selection boxes lies over the whole window)
    const canvas = await page.locator('canvas[data-engine^="three.js"]').boundingBox();
    say('canvas', { canvas });
    for (const [k, click] of plan.clicks.entries()) {
      await chooseImage(page, click.image);
      const classField = field(page, 'Class of next click');
      await classField.fill(click.class);
      await classField.press('Enter');
      await page.waitForTimeout(plan.settle_ms || 300); // the class reaches the server before the click
      await button(page, plan.arm).click();
      await waitForStatus(page, /click one pixel on an instance/);
      const at = viewPixel(canvas, click.xy, plan.camera);
      if (at.x < canvas.x || at.x >= canvas.x + canvas.width || at.y < canvas.y || at.y >= canvas.y + canvas.height) {
        throw new Error(`pixel ${click.xy} of ${click.image} lies outside the 3D view (${JSON.stringify(at)})`);
      }
      await page.mouse.click(at.x, at.y);
      const status = await waitForStatus(page, /^(added instance|.*: )/);
      await page.screenshot({ path: path.join(plan.screenshots, `click-${k + 1}.png`) });
      say('click', { k: k + 1, image: click.image, xy: click.xy, at, status });
      if (!status.startsWith('added instance')) throw new Error(`click ${k + 1} refused: ${status}`);
    }
    say('clicks', { listing: await field(page, 'Clicks').inputValue() });
    await button(page, plan.confirm).click();
    const status = await waitForStatus(page, /^writing the masks/);
    say('confirmed', { status });
  } catch (err) {
    failed = true;
    say('error', { message: String(err && err.stack || err) });
    await page.screenshot({ path: path.join(plan.screenshots, 'failure.png') }).catch(() => {});
  } finally {
    await context.close();
    fs.rmSync(profile, { recursive: true, force: true });
  }
  process.exit(failed ? 1 : 0);
})();
